"""Options several sub-commands take, each defined once: its spelling, type, default and help.

Where two commands used to spell one thing differently, the first spelling is the option and
the others stay as aliases (``--rig`` / ``--config``, ``--plan-points`` / ``--points``).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

INSTALLED_STORE = Path("/srv/tbp-rig/scans")
"""The rig PC's scan store (systemd/tbp-rig.tmpfiles)."""
DEV_STORE = Path("scans")
"""The development store, relative to the working folder: simulated scans, and every command on a
machine without the installed store."""
STORE_ENV = "TBP_STORE"
LOG_LEVELS = ("debug", "info", "warning", "error")


def rig(parser: argparse.ArgumentParser, help: str = "rig file (default: calibration_data/rig.yaml)") -> None:
    parser.add_argument("--rig", "--config", dest="rig", type=Path, default=None, metavar="FILE", help=help)


def hardware(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hardware", type=Path, default=None, metavar="FILE",
                        help="hardware file: how this PC reaches each device (default: hardware.yaml beside the rig file)")


def hardware_path(args: argparse.Namespace) -> Path:
    """--hardware, else hardware.yaml beside the rig file (--rig, else the default rig)."""
    from daemon.rig.hardware_config import default_hardware_path
    from planner.rig import DEFAULT_RIG_PATH

    return args.hardware or default_hardware_path(args.rig or DEFAULT_RIG_PATH)


def rig_and_hardware(args: argparse.Namespace, command: str) -> tuple[Any, Any] | None:
    """The rig file and its hardware file (--rig, --hardware); None, after one line on stderr
    naming the file and the key, when either is unusable (the caller exits 2)."""
    from daemon.rig.hardware_config import load_hardware
    from planner.rig import DEFAULT_RIG_PATH, RigConfigError, load_rig

    try:
        rig = load_rig(args.rig or DEFAULT_RIG_PATH)
        return rig, load_hardware(hardware_path(args), rig)
    except (RigConfigError, OSError) as exc:
        print(f"tbp {command}: {exc}", file=sys.stderr)
        return None


def state_dir(explicit: Path | None = None) -> Path:
    """Where the daemon keeps its ADB key: ``explicit``, $STATE_DIRECTORY (systemd's
    StateDirectory=), else ~/.local/state/tbp-rig."""
    if explicit is not None:
        return explicit
    state = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    return Path(state) if state else Path.home() / ".local" / "state" / "tbp-rig"


def store(parser: argparse.ArgumentParser) -> None:
    """``--store DIR`` (see :func:`store_root` for the default)."""
    parser.add_argument("--store", type=Path, default=None, metavar="DIR",
                        help=f"scan store folder (default ${STORE_ENV}; else with --sim ./{DEV_STORE}; else "
                             f"{INSTALLED_STORE} where it exists, ./{DEV_STORE} where not)")


def store_root(args: argparse.Namespace) -> Path:
    """The scan store an invocation means, one rule for every command: --store; else $TBP_STORE;
    else for a simulated rig (--sim: ``tbp scan``, ``tbp daemon``) the development store, so no
    simulated scan lands among patients' scans; else the installed store on a rig PC (where it
    exists) and the development store elsewhere. So on a development machine ``tbp daemon --sim``,
    ``tbp scan --sim``, ``tbp scans`` and the daemon's viewer all use ./scans."""
    if args.store is not None:
        return args.store
    if os.environ.get(STORE_ENV):
        return Path(os.environ[STORE_ENV])
    if getattr(args, "sim", False) or not INSTALLED_STORE.is_dir():
        return DEV_STORE
    return INSTALLED_STORE


def seed(parser: argparse.ArgumentParser, help: str) -> None:
    parser.add_argument("--seed", type=int, default=0, metavar="S", help=f"{help} (default 0)")


def plan_points(parser: argparse.ArgumentParser, default: int | None = None) -> None:
    shown = "the rig file's planner.points" if default is None else str(default)
    parser.add_argument("--plan-points", "--points", dest="plan_points", type=int, default=default,
                        metavar="N", help=f"surface samples for planning (default: {shown})")


def log_level(parser: argparse.ArgumentParser, default: str) -> None:
    parser.add_argument("--log-level", default=default, choices=LOG_LEVELS, help=f"(default {default})")


def socket(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--socket", type=Path, default=None, metavar="PATH",
                        help="control socket (default $TBP_CONTROL_SOCKET or /run/tbp-rig/control.sock)")


def time_scale(parser: argparse.ArgumentParser, default: float | None) -> None:
    shown = "as fast as possible" if default is None else f"{default:g}"
    parser.add_argument("--time-scale", type=float, default=default, metavar="X",
                        help=f"with --sim: virtual time runs at X times real time (default: {shown})")


def simulated_rig(parser: argparse.ArgumentParser) -> None:
    """``--sim`` and the simulated world's options (``tbp scan`` and ``tbp daemon``)."""
    parser.add_argument("--sim", action="store_true", help="simulated hardware, in this process")
    seed(parser, "simulated subject and noise seed (--sim)")
    parser.add_argument("--depth-decimation", type=int, default=2, metavar="N",
                        help="with --sim: simulated depth cameras render at 1/N resolution (default 2)")
    parser.add_argument("--subject", type=Path, default=None, metavar="MESH",
                        help="with --sim: the subject's mesh file (default: a body for --seed)")
    parser.add_argument("--no-panel", action="store_true", help="with --sim: a rig without a panel")
    parser.add_argument("--lesion-changes", type=lesion_changes, default=None, metavar="SEED",
                        help="with --sim: a follow-up visit of the subject, some of its larger spots grown "
                             "and new ones appeared, chosen by SEED (default: the skin as it is)")


TEXEL_RANGE_MM = (0.05, 50.0)


def body_texel(parser: argparse.ArgumentParser) -> None:
    """``--body-texel-mm``: the texel of the textured body written after each scan."""
    parser.add_argument("--body-texel-mm", type=float, default=None, metavar="MM",
                        help="texel side on the skin of the textured body written after each scan "
                             "(default: 0.7 of the best images' mm per pixel there; coarser is faster)")


def texel_problem(flag: str, value: float | None) -> str | None:
    """What is wrong with a texel option's value (None: nothing; None as the value is the default)."""
    low, high = TEXEL_RANGE_MM
    if value is not None and not low <= value <= high:
        return f"{flag} {value:g}: expected {low:g} to {high:g} mm"
    return None


def url_problem(flag: str, value: str | None) -> str | None:
    """What is wrong with an archive URL option's value (None: nothing, or not given): the
    site file's rule, an http:// or https:// URL (planner/schema/tables.py URL)."""
    from planner.schema.tables import URL

    if value is not None and (len(value) > 2048 or URL.fullmatch(value) is None):
        return f"{flag} {value[:80]!r}: expected an http:// or https:// URL"
    return None


def lesion_changes(text: str) -> Any:
    """``--lesion-changes SEED``: the seeded LesionChanges (drivers/sim/skin_texture.py)."""
    from drivers.sim.skin_texture import LesionChanges, LesionChangesError

    try:
        return LesionChanges(int(text))
    except ValueError as exc:  # int() or LesionChangesError
        problem = exc if isinstance(exc, LesionChangesError) else f"lesion changes seed {text!r}: not a whole number"
        raise argparse.ArgumentTypeError(str(problem)) from exc
