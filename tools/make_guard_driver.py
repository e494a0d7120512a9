"""Writes tests/fixtures/guard_driver.pt, the trained driver of the closed-loop guard
(tests/driving/test_closed_loop_guard.py), from a centralized checkpoint.

The guard's driver is the centralized compact model of the documented recipe (since 2026-12-06 the
defaults give it one-link signal heads and a stop head, and red-line samples in the data set):

    crchfl-sumo dataset paper --out DATA --seed 0
    crchfl-sumo train DATA --out TRAIN --epochs 6 --seed 0 --precision fp32
    python tools/make_guard_driver.py TRAIN/checkpoint.pt

The fixture is the checkpoint without what only `train --resume` reads (the optimizers' state, two
thirds of the file): 2 MB of float32 weights and the settings a drive and a fine-tune read. After a
change to the network,
the renderer or the data set's expert, rebuild the fixture this way and set the test's floors to
what it then measures (the test's docstring says how).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from crchfl_sumo.learning.checkpoint import load_checkpoint, save_checkpoint

FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "guard_driver.pt"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--out", type=Path, default=FIXTURE)
    args = parser.parse_args()
    checkpoint = load_checkpoint(args.checkpoint)
    extra = {key: value for key, value in checkpoint.extra.items() if key != "resume"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(args.out, checkpoint.model_config, checkpoint.state_dict, extra)
    print(f"{args.checkpoint} -> {args.out} ({args.out.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
