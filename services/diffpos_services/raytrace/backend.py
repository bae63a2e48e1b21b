"""Sionna RT availability: the optional extra imported lazily, or an installation hint."""

from __future__ import annotations

import os
from pathlib import Path

from diffpos_services.errors import DiffposError
from diffpos_services.raytrace.corrections import apply_corrections

DEFAULT_LLVM_PATH = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
SIONNA_REQUIREMENT = "sionna-rt==2.2.0"
VARIANT = "llvm_ad_mono_polarized"
INSTALL_HINT = (
    "the ray tracer is an optional extra. Install it with\n"
    "    pip install -e '.[raytrace]'          (sionna-rt 2.2.0, about 350 MB)\n"
    "    apt-get install libllvm19             (Dr.Jit's CPU backend; LLVM 14/15 do not work)\n"
    f"and, if libLLVM is not at {DEFAULT_LLVM_PATH}, point DRJIT_LIBLLVM_PATH at it."
)


class RaytraceUnavailable(DiffposError, RuntimeError):
    """Sionna RT or its LLVM backend is missing; the message says how to install it.

    ``diffpos raytrace`` exits with status 3 for it.
    """

    exit_code = 3


def check_sionna() -> dict[str, str]:
    """Import Sionna RT with the LLVM variant, or explain how to install it.

    Sets ``DRJIT_LIBLLVM_PATH`` to :data:`DEFAULT_LLVM_PATH` if it is unset and that file
    exists (Debian's ``libllvm19``).

    Returns
    -------
    dict
        Versions: ``{"sionna-rt": ..., "mitsuba": ..., "drjit": ..., "libllvm": path}``.

    Raises
    ------
    RaytraceUnavailable
        With an installation hint naming what is missing.
    """
    if "DRJIT_LIBLLVM_PATH" not in os.environ and Path(DEFAULT_LLVM_PATH).exists():
        os.environ["DRJIT_LIBLLVM_PATH"] = DEFAULT_LLVM_PATH
    # sionna/mitsuba/drjit are the optional extra: imported here, never at module level
    try:
        import drjit  # noqa: F401
        import mitsuba as mi
    except ImportError as exc:
        raise RaytraceUnavailable(f"sionna-rt is not installed ({exc}): {INSTALL_HINT}") from None
    llvm = os.environ.get("DRJIT_LIBLLVM_PATH", "")
    try:
        mi.set_variant(VARIANT)
    except Exception as exc:  # Dr.Jit raises ImportError/RuntimeError/AttributeError here
        where = f"DRJIT_LIBLLVM_PATH={llvm}" if llvm else "no DRJIT_LIBLLVM_PATH set"
        raise RaytraceUnavailable(
            f"Mitsuba could not start its LLVM backend ({where}): {exc}. {INSTALL_HINT}"
        ) from None
    import drjit as dr

    try:
        llvm_version = tuple(dr.detail.llvm_version())
    except Exception:  # pragma: no cover - older Dr.Jit without the query
        llvm_version = ()
    if llvm_version and llvm_version[0] <= 15:
        # LLVM 14 is refused by Dr.Jit, LLVM 15 loads but aborts the process on the first solve
        raise RaytraceUnavailable(
            f"Dr.Jit loaded LLVM {'.'.join(map(str, llvm_version))} "
            f"({llvm or 'found on the library path'}), which crashes the ray tracer; "
            f"{INSTALL_HINT}")
    try:
        import sionna.rt as rt
    except Exception as exc:
        raise RaytraceUnavailable(f"sionna.rt failed to import ({exc}): {INSTALL_HINT}") from None

    version = str(getattr(rt, "__version__", "?"))
    fixes = apply_corrections(version)
    return {"sionna-rt": version, "corrections": ",".join(fixes), "mitsuba": mi.__version__,
            "drjit": dr.__version__, "libllvm": llvm, "variant": VARIANT,
            "llvm": ".".join(map(str, llvm_version))}
