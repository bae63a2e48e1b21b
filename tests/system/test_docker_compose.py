"""docker-compose.yml is checked without a Docker engine: structure, commands, endpoints, ports."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
from importlib import metadata
from pathlib import Path

import pytest
from diffpos_services.bus.session import check_endpoint
from diffpos_services.cli import main as cli

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker-compose.yml"


def _load_yaml(path: Path) -> dict:
    """PyYAML if importable, else the system python's PyYAML (not in the venv), else skip."""
    try:
        import yaml
    except ImportError:
        yaml = None
    if yaml is not None:
        return yaml.safe_load(path.read_text())
    py = shutil.which("python3", path="/usr/bin:/usr/local/bin")
    if py is None:
        pytest.skip("PyYAML is not installed")
    code = "import json, sys, yaml; json.dump(yaml.safe_load(open(sys.argv[1])), sys.stdout)"
    r = subprocess.run([py, "-c", code, str(path)], capture_output=True, text=True, timeout=30)
    if r.returncode != 0:
        pytest.skip(f"PyYAML is not installed (system python: {r.stderr.strip()[-200:]})")
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def compose() -> dict:
    return _load_yaml(COMPOSE)


def _router_config() -> dict:
    return json.loads((ROOT / "docker" / "zenoh-router.json5").read_text())


def test_router_is_the_official_image_pinned_to_the_wheel_version(compose):
    router = compose["services"]["router"]
    wheel = metadata.version("eclipse-zenoh")
    assert router["image"] == f"eclipse/zenoh:{wheel}"
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert f'"eclipse-zenoh=={wheel}"' in pyproject
    # the mounted config exists and is the one passed to zenohd
    mounts = {v.split(":")[1]: v.split(":")[0] for v in router["volumes"]}
    cfg_path = router["command"][router["command"].index("-c") + 1]
    assert (ROOT / mounts[cfg_path]).resolve() == (ROOT / "docker" / "zenoh-router.json5").resolve()
    cfg = _router_config()
    assert cfg["mode"] == "router"
    assert cfg["scouting"]["multicast"]["enabled"] is False


def test_every_service_command_parses_with_the_cli(compose):
    services = compose["services"]
    python_services = {k: v for k, v in services.items() if k != "router"}
    assert {"fusion", "recorder", "dashboard"} <= set(python_services)
    assert sum(k.startswith("anchor-") for k in python_services) >= 4
    for name, svc in python_services.items():
        assert svc["build"]["context"] == "." and svc["build"]["dockerfile"] == "Dockerfile"
        assert (ROOT / svc["build"]["dockerfile"]).exists()
        cmd = svc["command"]
        assert cmd[0] in cli.COMMANDS, f"{name}: unknown subcommand {cmd[0]!r}"
        parser = cli.build_parser(cmd[0])
        args = parser.parse_args(cmd[1:])  # SystemExit (test failure) on an unknown option
        assert args is not None


def test_endpoints_ports_and_ids_are_consistent(compose):
    services = compose["services"]
    listen = _router_config()["listen"]["endpoints"]
    assert len(listen) == 1
    port = int(listen[0].rsplit(":", 1)[1])
    assert f"127.0.0.1:{port}:{port}" in services["router"]["ports"]  # plain bus: loopback only
    expected = f"tcp/router:{port}"
    from diffpos_services.scenario_io import load_scenario

    for name, svc in services.items():
        if name == "router":
            continue
        cmd = svc["command"]
        connects = [cmd[i + 1] for i, a in enumerate(cmd) if a == "--connect"]
        assert connects == [expected], (name, connects)
        check_endpoint(connects[0])
        sites = [cmd[i + 1] for i, a in enumerate(cmd) if a == "--site"]
        assert sites == ["demo"], name
        if cmd[0] == "anchor":
            aid = cmd[cmd.index("--id") + 1]
            assert name == f"anchor-{aid}"
            scen = load_scenario(cmd[cmd.index("--scenario") + 1])
            assert aid in [a.id for a in scen.anchors]
        # the healthcheck uses the same endpoint and a liveliness key of this site
        test = svc["healthcheck"]["test"]
        if "health" in test:
            hc = test[test.index("diffpos") + 1:]
            assert hc[hc.index("--connect") + 1] == expected
            key = hc[hc.index("--liveliness") + 1]
            assert key.startswith("diffpos/demo/alive/")
            if cmd[0] == "anchor":
                assert key == f"diffpos/demo/alive/anchor/{cmd[cmd.index('--id') + 1]}"
            with pytest.raises(SystemExit):  # options parse (then --help exits)
                cli.main([*hc, "--help"])
    dash = services["dashboard"]["command"]
    for opt in ("--web-port", "--grpc-port"):
        p = dash[dash.index(opt) + 1]
        assert f"{p}:{p}" in services["dashboard"]["ports"], opt


def test_healthchecks_dependencies_and_init(compose):
    services = compose["services"]
    for name, svc in services.items():
        assert svc.get("init") is True, f"{name}: init: true (signals reach the process, zombies reaped)"
        hc = svc.get("healthcheck")
        assert hc and hc.get("test"), f"{name}: healthcheck missing"
        for dep, cond in (svc.get("depends_on") or {}).items():
            assert dep in services, (name, dep)
            assert cond["condition"] in ("service_started", "service_healthy",
                                         "service_completed_successfully")
            if cond["condition"] == "service_healthy":
                assert services[dep].get("healthcheck"), (name, dep)
        if name != "router":
            assert "router" in svc["depends_on"], name
    # no dependency cycles
    graph = {n: set(s.get("depends_on") or {}) for n, s in services.items()}
    seen: dict[str, int] = {}

    def visit(n: str) -> None:
        assert seen.get(n) != 1, f"dependency cycle through {n}"
        if seen.get(n) == 2:
            return
        seen[n] = 1
        for d in graph[n]:
            visit(d)
        seen[n] = 2

    for n in graph:
        visit(n)


def test_dockerfile_installs_the_package_and_runs_the_cli():
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11", text, re.M)
    for d in ("diffpos", "services", "schemas", "scenarios"):
        assert re.search(rf"^COPY {d} \./{d}$", text, re.M), d
        assert (ROOT / d).is_dir()
    assert 'ENTRYPOINT ["diffpos"]' in text
    joined = text.replace("\\\n", " ")  # line continuations
    run = " ".join(line for line in joined.splitlines() if line.startswith("RUN"))
    assert "pip install" in run
    shlex.split(run)  # well-formed shell words (raises on a dangling quote or escape)
