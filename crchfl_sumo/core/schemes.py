"""The federated schemes, named once: CRCHFL (the paper's), its baselines HFL and SFL; the other models that drive."""

from __future__ import annotations

from typing import Literal, get_args

Scheme = Literal["crchfl", "hfl", "sfl"]
SCHEMES: tuple[Scheme, ...] = get_args(Scheme)  # in the order tables and figures list them
DISPLAY_NAMES: dict[str, str] = {"crchfl": "CRCHFL", "hfl": "HFL", "sfl": "SFL"}

# The models that drive beside the schemes' (reproduce's labels: folders, summary keys, table rows).
CENTRALIZED = "centralized"  # one model trained on every vehicle's data: the upper bound
CENTRALIZED_DAGGER = "centralized_dagger"  # the centralized model refined by DAgger (driving.dagger)
REFERENCE = "reference"  # the scripted route-following driver (driving.policies.RoutePolicy)
MODEL_LABELS = (*SCHEMES, CENTRALIZED, CENTRALIZED_DAGGER, REFERENCE)  # in the order tables list them
