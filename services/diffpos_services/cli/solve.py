"""Position fixes from JSON Lines problems on stdin (D-NLS, LLS, IPPA, M-NLS)

A filter: reads one positioning problem per line (JSON object) from stdin or --input, writes
exactly one result line (JSON object) to stdout for every input line that is not blank, in
the same order. Blank (whitespace-only) lines are skipped without a result, but counted in
the result's "line" number. Problems are solved in batches (--batch lines at a time) with
the vectorised estimators of diffpos.estimators.

Coordinates (building frame): the facade with the windows is the plane y = 0, the inside is
y > 0, anchors are outside (y < 0: an anchor with y >= 0 makes the line invalid_input, naming
the anchor), x runs along the window edges, z is up. SI units.

Problem fields (JSON Schema: schemas/solve_problem.v1.json):
  anchors_m        [[x, y, z], ...]   anchor positions [m], at least 3, all with y < 0
  ranges_m         [r, ...]           measured ranges [m], one per anchor; null = not measured
  sigmas_m         s or [s, ...]      ranging standard deviations [m] (optional; without them
                                      the residual test is skipped and the covariance is
                                      scaled by the a-posteriori variance factor)
  window_height_m  w                  window height [m] (required for dnls unless --scenario)
  edge_x_m         [x1, x2]           extent of the window edges along x [m] (default: the
                                      --scenario building's, else unbounded)
  delta_m          d                  Case-2 offset of the node below mid-window [m] (default 0)
  method           "dnls" | "lls" | "ippa" | "mnls"   (default dnls, or --method; mnls needs
                                      --scenario)
  gating           true | false | {"false_alarm_probability": 1e-3, "max_exclusions": 2,
                                      "pregate": true, "multistart_exclusion": true,
                                      "z_range_m": [0, 1e9] or null}   (dnls only; default true;
                                      a fix outside z_range_m is gating_failed)
  loss             "linear" | "huber" | "soft_l1"   (dnls only; default linear)
  x0_m             [x, y, z]          one start instead of the floor grid (dnls, ippa)
  z_starts_m       [z, ...]           start heights (default every 3 m from 0 to 30 m)
  nlos             bool or [bool,...] IPPA NLoS flags (default all true)
  nlos_bias_m      b or [b, ...]      IPPA mean NLoS bias subtracted from the ranges [m]
  snr_db           [s, ...]           measured SNR of each first arrival [dB], null = unknown
                                      (mnls: with the --scenario radio, a link too strong to be
                                      diffracted is not modelled as a diffraction)
  id               any JSON value     echoed back unchanged

M-NLS (method mnls) is the mechanism-aware estimator (diffpos.estimators.mnls.solver): every floor of
the building a hypothesis, the first-arrival mechanism of each link (window, reflections,
diffraction over the physical edges, double bounces) a latent choice, a one-sided robust
likelihood, a floor posterior and a covariance that includes the model ambiguity. It needs
the building's floors, window band, depth and edges, which a problem line does not carry:
--scenario FILE gives them for every line (a site is one building; the scenario TOML is the
file the fusion and the emulator read). Its radio sets the error floor of the ranging sigmas,
the NLoS excess scale c/B and the SNR test. gating: mnls runs its own residual test (only
false_alarm_probability applies); loss, x0_m, z_starts_m, nlos are not used by mnls. With
--scenario, dnls lines without window_height_m / edge_x_m take the building's.

Result fields (JSON Schema: schemas/solve_result.v1.json): line, id, status (ok,
ok_unverified, not_converged, not_identifiable, too_few_anchors, gating_failed,
invalid_input), message, method, position_m, covariance_m2 (3x3, the inverse FIM at the
estimate; covariance_model says which model), peb_m, z_bound_m, iterations, converged,
used_anchors, excluded_anchors ([{"index", "reason"}]), residuals_m (null where unused),
test_statistic, test_threshold, floor and floor_probability (mnls: the most probable floor,
0 = the building's lowest, and the posterior of every floor; null for the other methods).
Numbers that do not exist are null. Only ok and ok_unverified publish a position: with any
other status position_m, covariance_m2, peb_m, z_bound_m, floor and floor_probability are
null (the fit is not trustworthy; message, residuals and the test say why).

A bad line (invalid JSON, wrong lengths, NaN/inf, negative range, fewer than 3 anchors, unknown
field, a value beyond the limits below, a line longer than --max-line-bytes, JSON nested too
deeply, bytes that are not UTF-8, an anchor not outside) gives a result with status
"invalid_input" and a message naming the field; the filter keeps going with the next line.

Limits (the work of one line is bounded; a line beyond them is invalid_input naming the
limit): --max-line-bytes bytes per line, --max-anchors anchors and --max-starts z_starts_m
per problem (the solver's work grows with anchors^2 x starts; raise them up to 1024 anchors
and 1000 starts if you need to), |coordinates|, ranges, sigmas and lengths at most 1e7 m, an
id of at most 1000 characters of JSON. The exit status is 0 unless --strict is given and
some line was invalid (1), an option is out of range (2) or the input cannot be read (2).

examples:
  echo '{"anchors_m": [[-15,-20,1],[0,-15,0],[0,-7,4],[15,-20,1]],
         "ranges_m": [32.233, 23.711, 15.058, 30.315], "sigmas_m": 0.005, "window_height_m": 1.0}' \\
    | tr -d '\\n' | diffpos solve
  diffpos solve --input problems.jsonl > fixes.jsonl
  diffpos solve --method lls --strict < problems.jsonl
  diffpos solve --batch 1 < fifo         answer each line as soon as it arrives
  diffpos solve --method mnls --scenario scenarios/paper.toml < problems.jsonl

From Python: diffpos_services.solve.solve_records(list_of_problem_dicts, scenario=...) returns
the result dicts; diffpos.estimators.dnls.solver / lls / ippa / mnls work on numpy arrays directly.
"""

from __future__ import annotations

import argparse
import gc
import sys
from collections.abc import Callable, Iterator
from typing import BinaryIO, TextIO

import msgspec

from diffpos.scenario import Scenario, ScenarioError
from diffpos_services.errors import ConfigError
from diffpos_services.scenario_io import load_scenario
from diffpos_services.wire.solve_io import (
    DEFAULT_MAX_ANCHORS,
    DEFAULT_MAX_STARTS,
    MAX_ANCHORS,
    MAX_LINE_BYTES,
    MAX_Z_STARTS,
    METHODS,
    Limits,
    read_lines,
)

#: one result line's JSON (msgspec: ~8x cheaper than json.dumps); the records hold no NaN:
#: FixResult.to_records turns non-finite numbers into null
_ENCODER = msgspec.json.Encoder()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--input", "-i", metavar="FILE",
                        help="read problems from FILE instead of stdin ('-' = stdin)")
    parser.add_argument("--method", choices=METHODS, default="dnls",
                        help="method for problems without a 'method' field (default dnls; "
                        "mnls needs --scenario)")
    parser.add_argument("--scenario", metavar="FILE",
                        help="scenario TOML file or shipped name: the building every line is "
                        "in (floors, window band, depth, edges) and its radio; needed by mnls, "
                        "the default window_height_m / edge_x_m of dnls (default: none)")
    parser.add_argument("--batch", type=int, default=256, metavar="N",
                        help="solve N lines together (default 256; 1 = answer every line "
                        "as soon as it is read)")
    parser.add_argument("--strict", action="store_true",
                        help="exit with status 1 if any line was invalid (all lines are "
                        "still answered)")
    parser.add_argument("--max-line-bytes", type=int, default=MAX_LINE_BYTES, metavar="N",
                        help=f"longer lines are answered with invalid_input without being "
                        f"held in memory (default {MAX_LINE_BYTES})")
    parser.add_argument("--max-anchors", type=int, default=DEFAULT_MAX_ANCHORS, metavar="N",
                        help=f"a problem with more anchors is answered with invalid_input "
                        f"(default {DEFAULT_MAX_ANCHORS}, at most {MAX_ANCHORS}; the work "
                        "per problem grows with the square of the anchor count)")
    parser.add_argument("--max-starts", type=int, default=DEFAULT_MAX_STARTS, metavar="N",
                        help=f"a problem with more z_starts_m is answered with invalid_input "
                        f"(default {DEFAULT_MAX_STARTS}, at most {MAX_Z_STARTS})")


def _limits(args: argparse.Namespace) -> Limits:
    """The per-line limits of the options; :class:`ConfigError` (exit 2) if out of range."""
    if args.batch < 1:
        raise ConfigError(f"--batch must be >= 1, got {args.batch}")
    return Limits(max_anchors=args.max_anchors, max_starts=args.max_starts,
                  max_line_bytes=args.max_line_bytes)


def _scenario(args: argparse.Namespace) -> Scenario | None:
    """``--scenario``'s scenario (None without it); :class:`ConfigError` (exit 2) if invalid."""
    if args.scenario is None:
        if args.method == "mnls":
            raise ConfigError("--method mnls needs the building: give --scenario FILE")
        return None
    try:
        return load_scenario(args.scenario)
    except ScenarioError as exc:
        raise ConfigError(f"--scenario: {exc}") from None


def _write_results(stream: BinaryIO | TextIO, args: argparse.Namespace, limits: Limits,
                   scenario: Scenario | None, solve_lines: Callable[..., Iterator[dict]]) -> int:
    """Solve the stream's lines to stdout with ``solve_lines``
    (:func:`diffpos_services.solve.solve_lines`); the number of invalid lines."""
    invalid = 0
    out = getattr(sys.stdout, "buffer", None)
    if out is None:  # a text-only stdout (tests replacing sys.stdout)
        out = sys.stdout
        enc = lambda recs: _ENCODER.encode_lines(recs).decode()  # noqa: E731
    else:
        sys.stdout.flush()  # anything printed before goes first
        enc = _ENCODER.encode_lines  # one JSON line per record, each ending in "\n"
    pending: list = []
    for rec in solve_lines(read_lines(stream, max_bytes=limits.max_line_bytes),
                           batch=args.batch, default_method=args.method, limits=limits,
                           scenario=scenario):
        if rec["status"] == "invalid_input":
            invalid += 1
        pending.append(rec)
        if len(pending) >= args.batch:  # one write per solved batch (--batch 1: every line)
            out.write(enc(pending))
            out.flush()
            pending.clear()
    if pending:
        out.write(enc(pending))
    out.flush()
    return invalid


def run(args: argparse.Namespace) -> int:
    # the estimators (numba kernels): not for --help; imported before gc.freeze() below
    from diffpos_services.solve import solve_lines

    limits = _limits(args)
    scenario = _scenario(args)
    # Everything alive now (modules, numba's compiled kernels: hundreds of thousands of
    # objects) outlives the solving: moved out of the cyclic collector's generations, so the
    # collections that the per-line records trigger no longer walk it (measured: 100k lines
    # ~2 s less CPU; results unchanged). Undone at the end for callers in the same process.
    gc.freeze()
    try:
        return _run_frozen(args, limits, scenario, solve_lines)
    finally:
        gc.unfreeze()


def _run_frozen(args: argparse.Namespace, limits: Limits, scenario: Scenario | None,
                solve_lines: Callable[..., Iterator[dict]]) -> int:
    from_file = bool(args.input and args.input != "-")
    if from_file:
        try:
            stream: BinaryIO | TextIO = open(args.input, "rb")
        except OSError as exc:
            print(f"diffpos solve: cannot read --input {args.input}: {exc.strerror}",
                  file=sys.stderr)
            return 2
    else:
        # bytes, so that a non-UTF-8 line is one invalid line, not the end of the input
        stream = getattr(sys.stdin, "buffer", sys.stdin)
    try:
        invalid = _write_results(stream, args, limits, scenario, solve_lines)
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):
            return 0
        print(f"diffpos solve: cannot read the input ({exc.strerror or exc})", file=sys.stderr)
        return 2
    finally:
        if from_file:
            stream.close()
    if invalid:
        print(f"diffpos solve: {invalid} invalid line(s)", file=sys.stderr)
    return 1 if (args.strict and invalid) else 0
