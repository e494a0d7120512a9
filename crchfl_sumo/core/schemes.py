"""The federated schemes, named once and described once: CRCHFL (the paper's), its baselines HFL and SFL; the
other models that drive."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

Scheme = Literal["crchfl", "hfl", "sfl"]
SCHEMES: tuple[Scheme, ...] = get_args(Scheme)  # in the order tables and figures list them
DISPLAY_NAMES: dict[str, str] = {"crchfl": "CRCHFL", "hfl": "HFL", "sfl": "SFL"}


@dataclass(frozen=True)
class SchemeShape:
    """What a scheme is made of (Algorithm 1 of the paper and its two baselines). Every decision that
    differs between the schemes (the settings they take, the transfers they make, the links they use)
    reads these, not the scheme's name.

    edge_tier: vehicles reach the cloud through edge servers (wireless to their edge, wireline on);
        without it, straight over the public macro link, one aggregation a round.
    pretraining: stage I, the cloud pretraining on samples the vehicles upload.
    planned: the resource optimizer (problem P) may choose the hyper-parameters.
    """

    edge_tier: bool
    pretraining: bool
    planned: bool


SHAPES: dict[str, SchemeShape] = {
    "crchfl": SchemeShape(edge_tier=True, pretraining=True, planned=True),
    "hfl": SchemeShape(edge_tier=True, pretraining=False, planned=False),
    "sfl": SchemeShape(edge_tier=False, pretraining=False, planned=False),
}

# The models that drive beside the schemes' (reproduce's labels: folders, summary keys, table rows).
CENTRALIZED = "centralized"  # one model trained on every vehicle's data: the upper bound
CENTRALIZED_DAGGER = "centralized_dagger"  # the centralized model refined by DAgger (driving.dagger)
REFERENCE = "reference"  # the scripted route-following driver (driving.policies.RoutePolicy)
MODEL_LABELS = (*SCHEMES, CENTRALIZED, CENTRALIZED_DAGGER, REFERENCE)  # in the order tables list them
