from __future__ import annotations

from collections import Counter

import pytest

from crchfl_sumo.accounting.ledger import GIB, KIB, MIB, Ledger, LedgerConfig, replay, resolve_sizes
from crchfl_sumo.accounting.schedules import (
    ByteSizes,
    Topology,
    Transfer,
    cloud_aggregation_schedule,
    cloud_round_schedule,
    edge_aggregation_schedule,
    schedule_bytes,
    stage_one_schedule,
)
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError

PAPER = resolve_sizes(LedgerConfig())
TOPO = Topology.from_counts((2, 3))
E = 150 * MIB


def _kinds(transfers):
    return Counter((t.link, t.direction, t.stage, t.payload) for t in transfers)


def test_paper_sizes_are_1024_based():
    assert PAPER.model_bytes == 150 * 1024 * 1024
    assert PAPER.sample_bytes == 1800 * 1024
    assert PAPER.budget_bytes == 20 * 1024**3


def test_real_and_measured_sizes_come_from_the_caller():
    cfg = LedgerConfig(model_size="real", sample_size="measured", budget_gb=1.0)
    sizes = resolve_sizes(cfg, real_model_bytes=12_345_678, measured_sample_bytes=40_000)
    assert (sizes.model_bytes, sizes.sample_bytes, sizes.budget_bytes) == (12_345_678, 40_000, GIB)
    with pytest.raises(CrchflError, match="real_model_bytes"):
        resolve_sizes(cfg, measured_sample_bytes=1)
    with pytest.raises(CrchflError, match="measured_sample_bytes"):
        resolve_sizes(cfg, real_model_bytes=1)


def test_budget_too_small_names_key_and_minimum():
    with pytest.raises(CrchflError, match=r"budget_gb.*at least 0\.1465"):
        resolve_sizes(LedgerConfig(budget_gb=0.1))


def test_config_from_toml_mapping_rejects_bad_values():
    cfg = from_mapping(LedgerConfig, {"rule": "physical", "budget_gb": 25}, "ledger")
    assert cfg.rule == "physical" and cfg.budget_gb == 25.0
    with pytest.raises(CrchflError, match="ledger.rule"):
        from_mapping(LedgerConfig, {"rule": "exact"}, "ledger")
    with pytest.raises(CrchflError, match="budget_gb"):
        LedgerConfig(budget_gb=-1)


def test_topology_from_counts_and_validation():
    assert TOPO.edges == ("edge0", "edge1")
    assert TOPO.vehicles == (("v0", "v1"), ("v2", "v3", "v4"))
    with pytest.raises(CrchflError):
        Topology(("a", "a"), (("v0",), ("v1",)))
    with pytest.raises(CrchflError):
        Topology(("cloud",), (("v0",),))


# ---- one round of each scheme, counted by hand


def test_hfl_round_paper_rule_by_hand():
    rnd = cloud_round_schedule("paper", "hfl", TOPO, PAPER, cloud_interval=1)
    # 5 uploads + 2 edge->cloud + 2 cloud->edge + 5 edge->vehicle = 14 models
    assert _kinds(rnd) == {
        ("wireless", "uplink", "II", "model"): 5,
        ("wireline", "uplink", "III", "model"): 2,
        ("wireline", "downlink", "III", "model"): 2,
        ("wireless", "downlink", "III", "model"): 5,
    }
    assert schedule_bytes(rnd) == 14 * E
    assert [(t.sender, t.receiver) for t in rnd[:2]] == [("v0", "edge0"), ("v1", "edge0")]


def test_sfl_round_by_hand_same_under_both_rules():
    for rule in ("paper", "physical"):
        rnd = cloud_round_schedule(rule, "sfl", TOPO, PAPER, cloud_interval=1)
        assert _kinds(rnd) == {
            ("wireless", "uplink", "III", "model"): 5,
            ("wireless", "downlink", "III", "model"): 5,
        }
        assert {t.receiver for t in rnd[:5]} == {"cloud"}
        assert schedule_bytes(rnd) == 10 * E
    with pytest.raises(ValueError):
        cloud_round_schedule("paper", "sfl", TOPO, PAPER, cloud_interval=2)


def test_edge_aggregation_without_cloud_differs_between_rules():
    paper = edge_aggregation_schedule("paper", "crchfl", TOPO, PAPER, followed_by_cloud=False)
    physical = edge_aggregation_schedule("physical", "crchfl", TOPO, PAPER, followed_by_cloud=False)
    assert _kinds(paper) == {("wireless", "uplink", "II", "model"): 5, ("wireline", "uplink", "III", "model"): 2}
    assert _kinds(physical) == {("wireless", "uplink", "II", "model"): 5, ("wireless", "downlink", "II", "model"): 5}
    # followed by a cloud aggregation, physically the edge -> cloud hop moves into the cloud aggregation
    last = edge_aggregation_schedule("physical", "crchfl", TOPO, PAPER, followed_by_cloud=True)
    cloud = cloud_aggregation_schedule("physical", "crchfl", TOPO, PAPER)
    assert len(last) == 5 and len(cloud) == 2 + 2 + 5


def test_cloud_interval_two_by_hand():
    # paper: 2 x (5 up + 2 edge->cloud) + 2 + 5 = 21; physical: (5 + 5) + (5) + (2 + 2 + 5) = 24
    assert schedule_bytes(cloud_round_schedule("paper", "crchfl", TOPO, PAPER, 2)) == 21 * E
    assert schedule_bytes(cloud_round_schedule("physical", "crchfl", TOPO, PAPER, 2)) == 24 * E
    # with one aggregation per cloud round both rules charge the same 14 models
    assert schedule_bytes(cloud_round_schedule("physical", "hfl", TOPO, PAPER, 1)) == 14 * E


def test_edge_without_vehicles_takes_no_part():
    topo = Topology(("edge0", "edge1"), (("v0", "v1"), ()))
    rnd = cloud_round_schedule("paper", "hfl", topo, PAPER, 1)
    assert schedule_bytes(rnd) == (2 + 1 + 1 + 2) * E
    assert "edge1" not in {t.sender for t in rnd} | {t.receiver for t in rnd}


def test_stage_one_samples_charged_twice_and_release_only_physically():
    samples = {"v0": 10, "v1": 0, "v3": 5}
    paper = stage_one_schedule("paper", "crchfl", TOPO, samples, PAPER)
    S = PAPER.sample_bytes
    assert [(t.link, t.sender, t.receiver, t.size_bytes) for t in paper] == [
        ("wireless", "v0", "edge0", 10 * S),
        ("wireless", "v3", "edge1", 5 * S),
        ("wireline", "edge0", "cloud", 10 * S),
        ("wireline", "edge1", "cloud", 5 * S),
    ]
    assert all(t.stage == "I" and t.payload == "samples" for t in paper)
    physical = stage_one_schedule("physical", "crchfl", TOPO, samples, PAPER)
    assert schedule_bytes(physical) == 30 * S + (2 + 5) * E
    assert stage_one_schedule("paper", "crchfl", TOPO, {}, PAPER) == ()
    sfl = stage_one_schedule("paper", "sfl", TOPO, samples, PAPER)
    assert schedule_bytes(sfl) == 15 * S
    with pytest.raises(ValueError):
        stage_one_schedule("paper", "crchfl", TOPO, {"v9": 1}, PAPER)


# ---- the stopping rule, replayed through the ledger


def _rounds(scheme, samples, rule="paper", sizes=PAPER, cloud_interval=1):
    ledger = Ledger(sizes)
    stage_one = stage_one_schedule(rule, scheme, TOPO, samples, sizes)
    rounds = replay(ledger, stage_one, cloud_round_schedule(rule, scheme, TOPO, sizes, cloud_interval))
    return rounds, ledger


def test_paper_round_counts_at_20_gb():
    # SFL 1500 MB per round -> 13; HFL 2100 MB per round -> 9 (paper, Section V-B)
    sfl, ledger = _rounds("sfl", {})
    assert sfl == 13
    assert not ledger.can_carry_model()
    hfl, ledger = _rounds("hfl", {})
    assert hfl == 9
    # the cut-short 10th round: 5 + 2 + 2 + 1 transfers fit in the last 1580 MB
    assert sum(r.cloud_round == 10 for r in ledger.records) == 10
    assert ledger.remaining_bytes == 1580 * MIB - 10 * E


def test_crchfl_keeps_nine_rounds_with_paper_like_pretraining():
    # 9 x 2100 MB leaves 1580 MB; two hops of 1800 KB per sample: at most 449 samples
    split = {"v0": 90, "v1": 90, "v2": 90, "v3": 90, "v4": 89}
    rounds, ledger = _rounds("crchfl", split)
    assert rounds == 9
    assert ledger.totals("stage")["I"] == 2 * 449 * 1800 * KIB
    one_more = dict(split, v4=90)
    assert _rounds("crchfl", one_more)[0] == 8


def test_replay_never_exceeds_budget_and_totals_add_up():
    rounds, ledger = _rounds("crchfl", {"v0": 300}, rule="physical", cloud_interval=2)
    assert ledger.spent_bytes <= ledger.budget_bytes
    assert sum(ledger.totals("stage").values()) == ledger.spent_bytes
    assert sum(ledger.totals("link").values()) == ledger.spent_bytes
    assert ledger.totals("payload")["samples"] == 2 * 300 * PAPER.sample_bytes


def test_replay_reports_stage_one_that_does_not_fit():
    sizes = ByteSizes(model_bytes=10, sample_bytes=100, budget_bytes=150)
    assert replay(Ledger(sizes), stage_one_schedule("paper", "crchfl", TOPO, {"v0": 1}, sizes),
                  cloud_round_schedule("paper", "crchfl", TOPO, sizes, 1)) == -1


def test_charge_refuses_overdraft():
    ledger = Ledger(ByteSizes(model_bytes=10, sample_bytes=1, budget_bytes=25))
    t = Transfer("wireless", "uplink", "II", "v0", "edge0", "model", 10)
    ledger.charge(t, cloud_round=1)
    ledger.charge(t, cloud_round=1)
    assert not ledger.can_carry_model() and ledger.remaining_bytes == 5
    with pytest.raises(ValueError):
        ledger.charge(t, cloud_round=1)
    with pytest.raises(ValueError):
        Ledger(ledger.sizes).charge(t, cloud_round=1, start_s=2.0, end_s=1.0)


# ---- persistence


@pytest.mark.parametrize("suffix", [".jsonl", ".csv"])
def test_save_load_round_trip(tmp_path, suffix):
    ledger = Ledger(PAPER)
    for i, t in enumerate(cloud_round_schedule("physical", "crchfl", TOPO, PAPER, 2)):
        ledger.charge(t, cloud_round=1, start_s=i * 0.5, end_s=i * 0.5 + 0.25)
    path = tmp_path / f"ledger{suffix}"
    ledger.save(path)
    back = Ledger.load(path, PAPER)
    assert back.records == ledger.records
    assert back.spent_bytes == ledger.spent_bytes
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temp file left behind


def test_load_rejects_other_sizes_and_garbage(tmp_path):
    path = tmp_path / "ledger.jsonl"
    Ledger(PAPER).save(path)
    other = ByteSizes(PAPER.model_bytes, PAPER.sample_bytes, 25 * GIB)
    with pytest.raises(CrchflError, match="original run"):
        Ledger.load(path, other)
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(CrchflError, match="not a readable ledger"):
        Ledger.load(bad, PAPER)
    with pytest.raises(CrchflError):
        Ledger(PAPER).save(tmp_path / "ledger.txt")
