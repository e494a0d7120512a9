"""The federated schemes, named once: CRCHFL (the paper's) and its baselines HFL and SFL."""

from __future__ import annotations

from typing import Literal, get_args

Scheme = Literal["crchfl", "hfl", "sfl"]
SCHEMES: tuple[Scheme, ...] = get_args(Scheme)  # in the order tables and figures list them
DISPLAY_NAMES: dict[str, str] = {"crchfl": "CRCHFL", "hfl": "HFL", "sfl": "SFL"}
