"""Is a service alive on the bus? A liveliness query for its token (container health checks).

``diffpos health --connect tcp/router:7447 --liveliness KEY`` exits 0 when the token KEY
(e.g. ``Keys(site).alive_fusion()``) is alive; on a secured bus ``--zenoh-config /security/zenoh/<user>.json5`` instead of
``--connect`` (the check logs in with that identity).
"""

from __future__ import annotations

import json

import zenoh

from diffpos_services.bus.security.configs import session_config
from diffpos_services.bus.security.profile import SecurityError
from diffpos_services.bus.session import ZenohSettings
from diffpos_services.errors import ConfigError

__all__ = ["health_check"]


def health_check(
    connect: list[str] | None,
    liveliness_key: str,
    *,
    timeout_s: float = 3.0,
    zenoh_config: str | None = None,
) -> bool:
    """True if a liveliness token matching ``liveliness_key`` is alive on the bus.

    ``zenoh_config``: the zenoh json5 file of an identity (secured bus); its
    ``connect/timeout_ms`` is replaced by ``timeout_s``. Without it, a plain client of the
    ``connect`` endpoints.

    Raises
    ------
    ConfigError
        ``zenoh_config`` is missing, rejected by zenoh or names a missing certificate.
    """
    if zenoh_config is not None:
        try:
            cfg, _ = session_config(zenoh_config, connect=connect or None)
        except SecurityError as exc:
            raise ConfigError(str(exc)) from None
        cfg.insert_json5("connect/timeout_ms", json.dumps(round(timeout_s * 1000)))
    else:
        cfg = ZenohSettings(connect=tuple(connect or ()),
                            connect_timeout_ms=round(timeout_s * 1000)).to_config()
    try:
        with zenoh.open(cfg) as session:
            replies = session.liveliness().get(liveliness_key, timeout=timeout_s)
            for reply in replies:
                if reply.ok is not None:
                    return True
    except zenoh.ZError:
        return False
    return False
