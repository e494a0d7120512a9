"""A run's append-only logs: ledger.jsonl, metrics.jsonl, stragglers.jsonl.

Each step appends its new records and lines; nothing is rewritten, so a step
writes as much as it adds, however long the run. A checkpoint keeps the
``Marks``: each log's byte offset and line count after its step. A resumed
run cuts every log back to its mark (dropping what a killed step appended
after its checkpoint) and reads the history back from it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from crchfl_sumo.accounting.ledger import Ledger, Record, jsonl_header, jsonl_lines
from crchfl_sumo.accounting.schedules import ByteSizes
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.result_files import METRICS_LOG_FILE
from crchfl_sumo.federation.state import FederationState

LEDGER, METRICS, STRAGGLERS = "ledger.jsonl", METRICS_LOG_FILE, "stragglers.jsonl"
LOGS = (LEDGER, METRICS, STRAGGLERS)

# name -> {"offset": bytes, "lines": entries (records or metric/straggler lines, the ledger's header not counted)}
Marks = dict[str, dict[str, int]]


def start_logs(out_dir: Path, sizes: ByteSizes) -> Marks:
    """Fresh logs (a ledger.jsonl holds just its header line); their marks."""
    texts = {LEDGER: jsonl_header(sizes), METRICS: "", STRAGGLERS: ""}
    for name, text in texts.items():
        (out_dir / name).write_text(text, encoding="utf-8")
    return {name: {"offset": len(text.encode("utf-8")), "lines": 0} for name, text in texts.items()}


def append_logs(out_dir: Path, state: FederationState, marks: Marks) -> Marks:
    """Append what ``state`` holds beyond ``marks`` to each log, on disk before returning; the new marks."""
    new = {
        LEDGER: jsonl_lines(state.records[marks[LEDGER]["lines"]:]),
        METRICS: [json.dumps(m) + "\n" for m in state.metrics[marks[METRICS]["lines"]:]],
        STRAGGLERS: [json.dumps(s) + "\n" for s in state.stragglers[marks[STRAGGLERS]["lines"]:]],
    }
    out: Marks = {}
    for name, lines in new.items():
        data = "".join(lines).encode("utf-8")
        with open(out_dir / name, "r+b") as handle:
            handle.seek(marks[name]["offset"])  # the mark, not the end: a killed step's tail is overwritten
            handle.write(data)
            handle.truncate()
            handle.flush()
            os.fsync(handle.fileno())  # before the checkpoint that names the new offset
        out[name] = {"offset": marks[name]["offset"] + len(data), "lines": marks[name]["lines"] + len(lines)}
    return out


def restore_logs(out_dir: Path, marks: Marks, sizes: ByteSizes) -> tuple[list[Record], list[dict], list[dict]]:
    """Cut each log back to its mark and read the history back: (records, metric lines, straggler lines)."""
    for name in LOGS:
        path = out_dir / name
        if not path.is_file() or path.stat().st_size < marks[name]["offset"]:
            raise CrchflError(
                f"{path}: missing or shorter than federation_state.pt says ({marks[name]['offset']} bytes); "
                "the folder was changed after the run; delete it to start afresh"
            )
        os.truncate(path, marks[name]["offset"])
    records = list(Ledger.load(out_dir / LEDGER, sizes).records)
    lines = {}
    for name in (METRICS, STRAGGLERS):
        try:
            lines[name] = [json.loads(line) for line in (out_dir / name).read_text(encoding="utf-8").splitlines()]
        except ValueError as exc:
            raise CrchflError(f"{out_dir / name}: not a readable log ({exc}); delete the folder to start afresh") from None
    for name, entries in ((LEDGER, records), (METRICS, lines[METRICS]), (STRAGGLERS, lines[STRAGGLERS])):
        if len(entries) != marks[name]["lines"]:
            raise CrchflError(
                f"{out_dir / name}: {len(entries)} entries where federation_state.pt says {marks[name]['lines']}; "
                "delete the folder to start afresh"
            )
    return records, lines[METRICS], lines[STRAGGLERS]
