"""CRCHFL on SUMO: hierarchical federated learning for end-to-end driving.

The package is layered along its data flow. Each subpackage may import only
from itself and the subpackages before it in LAYERS; the command line (cli/) is
last, on top.
tests/test_layers.py enforces the order.
"""

__version__ = "0.1.0"

LAYERS = (
    "core",  # errors, config, atomic writes, backends, packaged resources, figures
    "sumo",  # the scenario, the libsumo simulation, routes, maps, edge sites
    "links",  # wireless channel, association, transfer times, the federation's SUMO clock
    "vision",  # cameras, the static raster world, per-frame rendering, mosaics
    "data",  # expert labels, shards, data set generation, online collection, statistics
    "learning",  # the network, local training, trainers, FedAvg, checkpoints
    "accounting",  # per-scheme transfer schedules and the byte ledger
    "planning",  # problem P, the plan's timing, calibration, the plan command
    "federation",  # Algorithm 1's loop and a run from config to results folder
    "driving",  # dynamics, policies, the closed-loop drive, its plots
    "studies",  # reproduce, report, sweeps, simulate
    "cli",  # `crchfl-sumo <subcommand>`: parses arguments, calls the layers below, prints
)
