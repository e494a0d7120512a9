"""What the subcommands share: common arguments, and the check of --out against a command's settings."""

from __future__ import annotations

import argparse
from pathlib import Path

# Arguments that change where or how fast a command runs, not what its results are.
NOT_SETTINGS = {"run", "command", "verbose", "out", "overwrite", "resume", "jobs", "backend", "address", "no_video"}


def overwrite_argument(p: argparse.ArgumentParser, file: bool = False) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out if it exists" if file else
                   "write into --out even if it holds earlier results (files of the same names are replaced)")


def sumo_output_argument(p: argparse.ArgumentParser, of: str, note: str = "") -> None:
    """--sumo-output: SUMO's own files of the command's simulation run (sumo/outputs.py)."""
    from crchfl_sumo.sumo.outputs import SUMO_OUTPUTS

    p.add_argument("--sumo-output", default="",
                   help=f"SUMO's own files of {of}, as OUT/sumo-NAME.xml: any of {', '.join(SUMO_OUTPUTS)}, "
                   f"separated by commas{note}")


def output_folder(
    args, command: str, out: Path | None = None, resumable: bool = False, beside=(), extendable=(), formerly_kept=()
):
    """``with`` this around a command's work: core.outputs.output_dir checks --out (or ``out``) with its settings.

    ``extendable``: arguments a ``--resume`` may change (train's --epochs); every other setting it must keep.
    ``formerly_kept``: (argument, its choices) of extendable arguments that earlier versions kept, so
    that their folders still resume (whatever value they were run with).
    """
    from crchfl_sumo.core.outputs import fingerprint, output_dir

    settings = {k: v for k, v in sorted(vars(args).items()) if k not in NOT_SETTINGS}
    config = getattr(args, "config", None)
    files = [config] if config is not None and Path(config).is_file() else []
    kept = {k: v for k, v in settings.items() if k not in extendable}
    earlier = tuple(fingerprint({**kept, name: value}, files) for name, choices in formerly_kept for value in choices)
    return output_dir(
        args.out if out is None else out, command, fingerprint(settings, files), flag=f"{args.command} --out",
        replace=getattr(args, "overwrite", False), resumable=resumable, beside=beside,
        resume_fingerprint=fingerprint(kept, files) if extendable else None, earlier_resume_fingerprints=earlier,
        resuming=getattr(args, "resume", False),
    )


def leave_out_at_default(args, options) -> None:
    """Remove from ``args`` the options added to a command later that are at their default, so that a folder
    made before they existed still resumes (its settings fingerprint lacks them). ``options``: (names, at
    default) pairs."""
    for names, at_default in options:
        if at_default:
            for name in names:
                delattr(args, name)


def comma_list(text: str) -> tuple[str, ...]:
    """'a, b,,c' -> ('a', 'b', 'c'): the names of a comma-separated option."""
    return tuple(name.strip() for name in text.split(",") if name.strip())


def scenario_names() -> str:
    """The built-in scenarios as --help lists them (the packaged folders, so the list never goes stale)."""
    from crchfl_sumo.core.resources import builtin_names

    return ", ".join(builtin_names())


def scenario_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help=f"built-in scenario name ({scenario_names()}), a folder laid out as one, "
                        "or a .sumocfg path")


def backend_arguments(
    p: argparse.ArgumentParser,
    what: str = "where training runs: in this process (local) or as Ray tasks; overrides [backend] kind",
) -> None:
    p.add_argument("--backend", choices=("local", "ray"), default=None, help=what)
    p.add_argument("--address", default=None,
                   help="Ray cluster to join: 'auto' (this machine's) or HOST:PORT; default: start a local Ray runtime")
