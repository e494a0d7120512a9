"""The subcommand whose work lives in learning/: train."""

from __future__ import annotations

import argparse
from pathlib import Path

from crchfl_sumo.cli.arguments import comma_list, leave_out_at_default, output_folder, overwrite_argument
from crchfl_sumo.cli.progress_bars import ProgressBars
from crchfl_sumo.core.numbers import MAX_EPOCHS, auto_or, integer_arg, number_arg, seed_arg
from crchfl_sumo.learning.settings import (
    ARCHS, AUTO_EMA_DECAY, CLASS_WEIGHTINGS, MAX_DRAW_WEIGHT, MAX_RED_WINDOW_M, MAX_YIELD_WINDOW_M, PRECISIONS,
    SPEED_INPUTS, TrainConfig,
)


def add_train(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="data set folder (manifest.json and shards)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: metrics.jsonl, checkpoint.pt (checkpoint.prev.pt: the epoch before)")
    overwrite_argument(p)
    p.add_argument("--epochs", type=integer_arg(1, MAX_EPOCHS, "a number of epochs"), default=10,
                   help="epochs over all training shards (default 10)")
    p.add_argument("--size", choices=("compact", "paper"), default="compact", help="model size (default compact)")
    p.add_argument("--arch", choices=ARCHS, default="cil",
                   help="cil (default: normalised, one steer head per route command) or paper (the paper's network)")
    p.add_argument("--seed", type=seed_arg, default=0, help="seed of initialisation and shuffling (default 0)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto", help="default: cuda if present")
    p.add_argument("--deterministic", action="store_true", help="deterministic algorithms (bit-exact reruns)")
    p.add_argument("--precision", choices=PRECISIONS, default=TrainConfig.precision,
                   help=f"forward pass in float32, under bfloat16 autocast, or auto: bf16 where the device has "
                   f"bfloat16 arithmetic, else fp32 (default {TrainConfig.precision}; docs/model.md measures both)")
    p.add_argument("--resume", action="store_true",
                   help="continue the training in --out after its last checkpointed epoch (the same command line; "
                   "--epochs may be raised, and --precision named to continue in the precision the epochs trained in)")
    p.add_argument("--red-weight", type=number_arg(1, MAX_DRAW_WEIGHT, "a draw multiplier (1 = off)"),
                   default=TrainConfig.red_weight,
                   help="draw samples at a red or yellow signal within --red-window-m this many times as often "
                   f"(default {TrainConfig.red_weight:g}: off; needs a data set of format 5)")
    p.add_argument("--red-window-m", type=number_arg(0, MAX_RED_WINDOW_M, "metres before a stop line", lo_open=True),
                   default=TrainConfig.red_window_m,
                   help=f"metres before a stop line that --red-weight covers (default {TrainConfig.red_window_m:g})")
    p.add_argument("--yield-weight", type=number_arg(1, MAX_DRAW_WEIGHT, "a draw multiplier (1 = off)"),
                   default=TrainConfig.yield_weight,
                   help="draw samples whose nearest junction foe to yield to is within --yield-window-m of the "
                   f"conflict point this many times as often (default {TrainConfig.yield_weight:g}: off; needs a "
                   "data set of format 5)")
    p.add_argument("--yield-window-m", type=number_arg(0, MAX_YIELD_WINDOW_M, "metres from the conflict point",
                                                       lo_open=True),
                   default=TrainConfig.yield_window_m,
                   help="metres of the foe from the conflict point that --yield-weight covers (default "
                   f"{TrainConfig.yield_window_m:g})")
    p.add_argument("--class-weighting", choices=CLASS_WEIGHTINGS,
                   default=TrainConfig.class_weighting,
                   help=f"weights of the steer classes in the loss (default {TrainConfig.class_weighting}); on the "
                   "multi-lane grid 'none' kept the straight head straight (docs/measurements.md)")
    p.add_argument("--ema-decay", type=auto_or(number_arg(0, 1, "a decay per step (0 = off)", hi_open=True)),
                   default="auto",
                   help="keep, evaluate and save an exponential moving average of the weights over the steps, with "
                   f"this decay per step; 0: off (default auto: {AUTO_EMA_DECAY:g}, about the last 500 steps, or the "
                   "last two epochs' steps where they are fewer; a folder resumed keeps its own; docs/model.md)")
    p.add_argument("--speed-input", choices=tuple(SPEED_INPUTS), default="none",
                   help="the ego's speed as an input of the throttle/brake branch (longitudinal) or of both branches; "
                   "default none (the paper's); measured in docs/measurements.md")
    p.add_argument("--command-pedals", action="store_true",
                   help="the route command conditions the throttle/brake branch too (model.command_pedals): a "
                   "lane's heads show one light per movement, and only the command tells which is the car's")
    p.add_argument("--stop-head", action=argparse.BooleanOptionalAction, default=None,
                   help="branch I also learns the distance to a red or yellow signal's stop line, and the controller "
                   "slows to stop before it (model.stop_head; needs a data set of format 5; docs/model.md); default: "
                   "on where the data set holds signal states")
    p.add_argument("--red-hold", action="store_true",
                   help="while the route's next signal shows red, the target-speed label stops the car before the "
                   "line (model.red_hold; needs a data set of format 5; docs/model.md)")
    p.add_argument("--train-towns", type=comma_list, default=None,
                   help="train on these towns' training shards only, separated by commas (default: every town; "
                   "the test shards stay whole): train in town01, drive in town02 to measure generalisation")


def run_train(args) -> int:
    from crchfl_sumo.learning.centralized import train_command

    auto_ema = args.ema_decay == "auto"  # resolved from the data or the resumed checkpoint (train_command)
    # --resume --epochs N continues to N; --precision may change too (the checkpoint checks it against the
    # precision its epochs trained in), which folders marked while it was kept still allow
    config = TrainConfig(device=args.device, deterministic=args.deterministic, precision=args.precision,
                         red_weight=args.red_weight, red_window_m=args.red_window_m,
                         yield_weight=args.yield_weight, yield_window_m=args.yield_window_m,
                         class_weighting=args.class_weighting,
                         ema_decay=0.0 if auto_ema else args.ema_decay)  # refused before any file
    speed_input, stop_head, command_pedals, red_hold = args.speed_input, args.stop_head, args.command_pedals, args.red_hold
    train_towns = args.train_towns
    leave_out_at_default(args, ((("red_weight", "red_window_m"), args.red_weight == TrainConfig.red_weight),
                                (("yield_weight", "yield_window_m"), args.yield_weight == TrainConfig.yield_weight),
                                (("class_weighting",), args.class_weighting == TrainConfig.class_weighting),
                                (("ema_decay",), auto_ema),
                                (("speed_input",), speed_input == "none"), (("stop_head",), args.stop_head is None),
                                (("command_pedals",), not args.command_pedals), (("red_hold",), not args.red_hold),
                                (("train_towns",), train_towns is None)))
    with output_folder(args, "train", extendable=("epochs", "precision"), formerly_kept=(("precision", PRECISIONS),)):
        with ProgressBars("sample") as bars:
            last = train_command(args.dataset, args.out, args.epochs, args.size, args.arch, config, args.seed,
                                 resume=args.resume, overwrite=args.overwrite, progress=bars, speed_input=speed_input,
                                 stop_head=stop_head, command_pedals=command_pedals, red_hold=red_hold,
                                 train_towns=train_towns, auto_ema=auto_ema)
        straight = last["always_straight"]
    print(
        f"epoch {last['epoch']}: test loss {last['loss']:.4f}, accuracy {last['accuracy']:.3f} "
        f"(always straight {straight['accuracy']:.3f}), balanced accuracy {last['balanced_accuracy']:.3f} "
        f"(always straight {straight['balanced_accuracy']:.3f}) -> {args.out}"
    )
    return 0
