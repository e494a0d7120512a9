"""The byte account: every transfer of a run against the budget, and the stopping rule.

* ``LedgerConfig`` (settings) resolves to ``ByteSizes`` (bytes). Units are
  1024-based throughout, as in the reference implementation: 1 KB = 1024 B,
  1 MB = 1024 KB, 1 GB = 1024 MB. So the paper's 150 MB model is 150 * 1024**2
  bytes, one 1800 KB sample is 1800 * 1024 bytes and the 20 GB budget is
  20 * 1024**3 bytes.
* ``Ledger`` charges the transfers the schedules list (schedules.py) against
  the budget, applies the stopping rule (training stops when the rest of the
  budget cannot carry one more model transfer; a cloud round counts only if
  all its transfers were charged), reports totals and is saved to / loaded
  from JSONL or CSV for resume. ``replay`` runs schedules through a ledger,
  so problem P prices a plan exactly as the loop will charge it.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Literal, Mapping, Sequence

from crchfl_sumo.accounting.schedules import LINKS, RULES, STAGES, ByteSizes, Direction, Link, Payload, Stage, Transfer
from crchfl_sumo.core.atomic import atomic_path
from crchfl_sumo.core.errors import CrchflError

KIB = 1024
MIB = 1024 * KIB
GIB = 1024 * MIB
MAX_SIZE = 1e9  # of nominal_model_mb, nominal_sample_kb and budget_gb: beyond it byte counts stop being exact


def gb_label(gb: float) -> str:
    """A budget in GB as summary keys and file names write it: 2.5 -> "2.5", 20.0 -> "20"."""
    return f"{gb:g}"


@dataclass(frozen=True)
class LedgerConfig:
    """Accounting settings (TOML table ``[ledger]``).

    rule: ``paper`` charges what the reference implementation charged,
        ``physical`` the bytes that really cross each link (docs/ledger.md).
    model_size: ``nominal`` charges ``nominal_model_mb`` per model transfer
        (the paper's 150 MB); ``real`` charges the serialized size of our own
        model, which the caller measures and passes to ``resolve_sizes``.
    nominal_model_mb: nominal model size [MB, 1 MB = 1024 * 1024 bytes].
    sample_size: ``nominal`` charges ``nominal_sample_kb`` per pretraining
        sample (the paper's 1800 KB: four PNGs); ``measured`` charges a size
        the caller measures on our data set and passes to ``resolve_sizes``.
    nominal_sample_kb: nominal sample size [KB, 1 KB = 1024 bytes].
    budget_gb: the total communication budget U_sum [GB, 1 GB = 1024**3 bytes].
    marks_gb: smaller budgets [GB] inside this one: for each, the run also keeps the best model among
        the evaluations made within that many bytes (best_model_within_<B>gb.pt, summary.json
        ``budget_marks``). What a scheme whose schedule does not depend on the budget (HFL, SFL)
        reaches under a smaller budget is a prefix of its run under this one (docs/reproduce.md).
    """

    rule: Literal["paper", "physical"] = "paper"
    model_size: Literal["nominal", "real"] = "nominal"
    nominal_model_mb: float = 150.0
    sample_size: Literal["nominal", "measured"] = "nominal"
    nominal_sample_kb: float = 1800.0
    budget_gb: float = 20.0
    marks_gb: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise CrchflError(f"ledger.rule: {self.rule!r} is not one of 'paper', 'physical'")
        if self.model_size not in ("nominal", "real"):
            raise CrchflError(f"ledger.model_size: {self.model_size!r} is not one of 'nominal', 'real'")
        if self.sample_size not in ("nominal", "measured"):
            raise CrchflError(f"ledger.sample_size: {self.sample_size!r} is not one of 'nominal', 'measured'")
        for key in ("nominal_model_mb", "nominal_sample_kb", "budget_gb"):
            value = getattr(self, key)
            if not math.isfinite(value) or value <= 0 or value > MAX_SIZE:
                raise CrchflError(f"ledger.{key} must be a number in (0, {MAX_SIZE:g}], got {value!r}")
        marks = list(self.marks_gb)
        if any(not isinstance(m, (int, float)) or isinstance(m, bool) or not math.isfinite(m) or m <= 0 for m in marks) \
                or marks != sorted(set(marks)):
            raise CrchflError(f"ledger.marks_gb: {marks}; give positive budgets in GB, increasing, each once")
        if marks and marks[-1] > self.budget_gb:
            raise CrchflError(f"ledger.marks_gb: {marks[-1]:g} exceeds budget_gb = {self.budget_gb:g}; "
                              "a mark lies within the budget")


def resolve_sizes(
    config: LedgerConfig,
    real_model_bytes: int | None = None,
    measured_sample_bytes: int | None = None,
    model_fraction: float = 1.0,
    upload_fraction: float | None = None,
) -> ByteSizes:
    """Settings -> sizes in bytes; checks the budget can carry at least one model transfer.

    ``model_fraction`` scales every model transfer and ``upload_fraction`` (default: the same) a
    vehicle's upload: an update codec's encoded size over the raw one (learning.codecs.encoded_fraction),
    so that both rules, the stopping rule and the allocator charge what the codec sends.
    """
    if config.model_size == "real":
        if real_model_bytes is None or real_model_bytes <= 0:
            raise CrchflError(
                "ledger.model_size = 'real' needs the serialized model size; "
                "pass real_model_bytes or set ledger.model_size = 'nominal'"
            )
        model_bytes = int(real_model_bytes)
    else:
        model_bytes = round(config.nominal_model_mb * MIB)
    if config.sample_size == "measured":
        if measured_sample_bytes is None or measured_sample_bytes <= 0:
            raise CrchflError(
                "ledger.sample_size = 'measured' needs the measured sample size; "
                "pass measured_sample_bytes or set ledger.sample_size = 'nominal'"
            )
        sample_bytes = int(measured_sample_bytes)
    else:
        sample_bytes = round(config.nominal_sample_kb * KIB)
    upload_bytes = max(1, round(model_bytes * (model_fraction if upload_fraction is None else upload_fraction)))
    model_bytes = max(1, round(model_bytes * model_fraction))
    budget_bytes = math.floor(config.budget_gb * GIB)
    if budget_bytes < min(model_bytes, upload_bytes):
        raise CrchflError(
            f"ledger.budget_gb = {config.budget_gb:g} cannot carry one model transfer of {model_bytes} bytes; "
            f"set budget_gb to at least {model_bytes / GIB:.4f} (1 GB = 1024**3 bytes)"
        )
    return ByteSizes(model_bytes=model_bytes, sample_bytes=sample_bytes, budget_bytes=budget_bytes,
                     vehicle_upload_bytes=0 if upload_bytes == model_bytes else upload_bytes)


def budget_marks_bytes(config: LedgerConfig) -> tuple[int, ...]:
    """The budget marks in bytes (as the budget: whole bytes, rounded down)."""
    return tuple(math.floor(m * GIB) for m in config.marks_gb)


# ---------------------------------------------------------------- topology


# ---------------------------------------------------------------- schedule


# ---------------------------------------------------------------- ledger


@dataclass(frozen=True)
class Record:
    """One charged transfer: the planned transfer, its cloud round (0 = stage I) and simulated times [s]."""

    link: Link
    direction: Direction
    stage: Stage
    sender: str
    receiver: str
    payload: Payload
    size_bytes: int
    cloud_round: int
    start_s: float
    end_s: float

    def to_dict(self) -> dict:
        # Flat: ten times faster than dataclasses.asdict (a deep copy).
        return {name: getattr(self, name) for name in _RECORD_FIELDS}


_RECORD_FIELDS = tuple(f.name for f in dataclasses.fields(Record))


# The record fields a ledger keeps byte totals by, and their values.
TOTALLED = {"link": LINKS, "stage": STAGES, "payload": ("model", "samples"), "direction": ("uplink", "downlink")}


class Ledger:
    """Charges transfers against the budget; append-only.

    ``charge`` refuses a transfer that does not fit (the caller checks
    ``can_carry`` first); ``can_carry_model`` is the stopping rule.

    ``byte_totals`` (from an earlier ledger's ``byte_totals()``) continues that
    ledger without its records: the totals and the budget carry on, and
    ``records`` holds only what is charged from then on. So a long run need
    not carry every record from step to step.
    """

    def __init__(
        self, sizes: ByteSizes, records: Iterable[Record] = (), byte_totals: Mapping[str, Mapping[str, int]] | None = None
    ) -> None:
        self.sizes = sizes
        self._records: list[Record] = []
        self._totals = {by: {k: int((byte_totals or {}).get(by, {}).get(k, 0)) for k in keys} for by, keys in TOTALLED.items()}
        self._spent_bytes = sum(self._totals["link"].values())
        for record in records:
            self._append(record)

    @property
    def records(self) -> tuple[Record, ...]:
        return tuple(self._records)

    @property
    def budget_bytes(self) -> int:
        return self.sizes.budget_bytes

    @property
    def spent_bytes(self) -> int:
        return self._spent_bytes

    @property
    def remaining_bytes(self) -> int:
        return self.sizes.budget_bytes - self._spent_bytes

    def can_carry(self, size_bytes: int) -> bool:
        return size_bytes <= self.remaining_bytes

    def can_carry_model(self) -> bool:
        """The stopping rule: False once the rest of the budget cannot carry one more model transfer."""
        return self.can_carry(self.sizes.smallest_model_bytes)

    def charge(self, transfer: Transfer, *, cloud_round: int, start_s: float = 0.0, end_s: float = 0.0) -> Record:
        record = Record(**dataclasses.asdict(transfer), cloud_round=cloud_round, start_s=start_s, end_s=end_s)
        self._append(record)
        return record

    def _append(self, record: Record) -> None:
        if record.size_bytes < 0:
            raise ValueError(f"negative transfer size {record.size_bytes}")
        if not record.start_s <= record.end_s:
            raise ValueError(f"transfer ends before it starts: {record.start_s} > {record.end_s}")
        if record.size_bytes > self.remaining_bytes:
            raise ValueError(
                f"transfer of {record.size_bytes} bytes exceeds the remaining {self.remaining_bytes} bytes; "
                "check can_carry() before charging"
            )
        self._records.append(record)
        self._spent_bytes += record.size_bytes
        for by, totals in self._totals.items():
            totals[getattr(record, by)] += record.size_bytes

    def totals(self, by: Literal["link", "stage", "payload", "direction"]) -> dict[str, int]:
        """Bytes charged per value of one record field, e.g. ``totals("stage")`` -> {"I": .., "II": .., "III": ..}."""
        return dict(self._totals[by])

    def byte_totals(self) -> dict[str, dict[str, int]]:
        """Every total (``TOTALLED``): what a ledger continued without its records starts from."""
        return {by: dict(totals) for by, totals in self._totals.items()}

    # -- persistence

    def save(self, path: str | Path) -> None:
        """Write all records to ``.jsonl`` (first line: the sizes) or ``.csv``, atomically."""
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in (".jsonl", ".csv"):
            raise CrchflError(f"{path}: ledger files end in .jsonl or .csv")
        with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as handle:
            if suffix == ".jsonl":
                handle.write(jsonl_header(self.sizes))
                handle.writelines(jsonl_lines(self._records))
            else:
                writer = csv.DictWriter(handle, fieldnames=_RECORD_FIELDS)
                writer.writeheader()
                for record in self._records:
                    writer.writerow(record.to_dict())

    @classmethod
    def load(cls, path: str | Path, sizes: ByteSizes) -> "Ledger":
        """Read a ledger written by ``save``; a JSONL file must have been written with the same sizes."""
        path = Path(path)
        if not path.is_file():
            raise CrchflError(f"{path}: ledger file not found")
        try:
            with path.open(newline="", encoding="utf-8") as handle:
                if path.suffix.lower() == ".jsonl":
                    lines = [line for line in handle if line.strip()]
                    header = json.loads(lines[0]) if lines else {}
                    if header.get("sizes") != sizes.to_dict():
                        raise CrchflError(
                            f"{path}: written with sizes {header.get('sizes')}, resuming with {sizes.to_dict()}; "
                            "resume with the [ledger] settings of the original run"
                        )
                    rows = [json.loads(line) for line in lines[1:]]
                elif path.suffix.lower() == ".csv":
                    rows = list(csv.DictReader(handle))
                else:
                    raise CrchflError(f"{path}: ledger files end in .jsonl or .csv")
            records = [_record_from_row(row) for row in rows]
        except (ValueError, KeyError, TypeError) as exc:
            raise CrchflError(f"{path}: not a readable ledger ({exc}); delete it to start afresh") from None
        return cls(sizes, records)


def jsonl_header(sizes: ByteSizes) -> str:
    """The first line of a ledger.jsonl: the sizes it was charged with."""
    return json.dumps({"sizes": sizes.to_dict()}) + "\n"


def jsonl_lines(records: Iterable[Record]) -> list[str]:
    """One ledger.jsonl line per record (a run appends them step by step)."""
    return [json.dumps(record.to_dict()) + "\n" for record in records]


_FIELD_TYPES = {"size_bytes": int, "cloud_round": int, "start_s": float, "end_s": float}
_ALLOWED = {"link": LINKS, "direction": ("uplink", "downlink"), "stage": STAGES, "payload": ("model", "samples")}


def _record_from_row(row: Mapping[str, object]) -> Record:
    if set(row) != set(_RECORD_FIELDS):
        raise ValueError(f"fields {sorted(row)} differ from {list(_RECORD_FIELDS)}")
    values = {name: _FIELD_TYPES.get(name, str)(row[name]) for name in _RECORD_FIELDS}
    for name, allowed in _ALLOWED.items():
        if values[name] not in allowed:
            raise ValueError(f"{name} {values[name]!r} is not one of {allowed}")
    return Record(**values)


# ---------------------------------------------------------------- replay


def charge_all(ledger: Ledger, transfers: Iterable[Transfer], *, cloud_round: int) -> bool:
    """Charge ``transfers`` in order until one does not fit; True if all were charged.

    For model transfers "does not fit" is exactly the stopping rule. Times are
    left at 0: the federation loop charges with real simulated times itself.
    """
    for transfer in transfers:
        if not ledger.can_carry(transfer.size_bytes):
            return False
        ledger.charge(transfer, cloud_round=cloud_round)
    return True


def replay(
    ledger: Ledger,
    stage_one: Sequence[Transfer],
    cloud_round: Sequence[Transfer],
    max_rounds: int | None = None,
) -> int:
    """Charge stage I, then whole cloud rounds until the stopping rule; returns the completed cloud rounds.

    Stops early at ``max_rounds``. A round cut short by the budget leaves its
    charged transfers in the ledger (the bytes were spent) but is not counted.
    Returns -1 if stage I itself does not fit.
    """
    if not cloud_round:
        raise ValueError("a cloud round with no transfers would never exhaust the budget")
    if not charge_all(ledger, stage_one, cloud_round=0):
        return -1
    rounds = 0
    while ledger.can_carry_model() and (max_rounds is None or rounds < max_rounds):
        if not charge_all(ledger, cloud_round, cloud_round=rounds + 1):
            break
        rounds += 1
    return rounds
