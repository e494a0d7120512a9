"""core.outputs: an output folder is checked before any work, and whose results it holds is known."""

import json
import os

import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.outputs import (
    fingerprint,
    marker_path,
    markers,
    output_dir,
    prepare_output_dir,
    prepare_output_file,
)


def test_a_new_folder_is_created_and_marked(tmp_path):
    out = prepare_output_dir(tmp_path / "a" / "b", "simulate", "f1")
    assert out.is_dir()
    assert json.loads(marker_path(out, "simulate").read_text()) == {"command": "simulate", "fingerprint": "f1"}
    assert markers(out) == {"simulate": {"command": "simulate", "fingerprint": "f1"}}
    assert sorted(p.name for p in out.iterdir()) == [".crchfl-sumo-simulate.json"]  # the probe file is gone


def test_a_file_or_a_folder_inside_a_file_is_refused(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(CrchflError, match=r"simulate --out .*/f: is a file, not a folder"):
        prepare_output_dir(tmp_path / "f", "simulate", flag="simulate --out")
    with pytest.raises(CrchflError, match="cannot create the folder"):
        prepare_output_dir(tmp_path / "f" / "sub", "simulate")
    assert (tmp_path / "f").read_text() == "x"


def test_an_unwritable_folder_is_refused(tmp_path, monkeypatch):
    import crchfl_sumo.core.outputs as outputs

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(outputs.tempfile, "mkstemp", refuse)  # root writes anywhere: the probe is made to fail
    with pytest.raises(CrchflError, match=r"the folder is not writable \(Permission denied\)"):
        prepare_output_dir(tmp_path, "train")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_refused(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(CrchflError, match="not writable"):
            prepare_output_dir(folder, "train")
    finally:
        folder.chmod(0o755)


def test_the_same_settings_rerun_other_settings_or_commands_are_refused(tmp_path):
    prepare_output_dir(tmp_path, "train", "f1")
    (tmp_path / "metrics.jsonl").write_text("{}\n")
    prepare_output_dir(tmp_path, "train", "f1")  # the same command and settings: a rerun writes the same files
    with pytest.raises(CrchflError, match="holds results of `crchfl-sumo train` with other settings.*--overwrite"):
        prepare_output_dir(tmp_path, "train", "f2")
    with pytest.raises(CrchflError, match="holds the results of `crchfl-sumo train`; choose another folder"):
        prepare_output_dir(tmp_path, "simulate", "f1")
    prepare_output_dir(tmp_path, "train", "f2", replace=True)  # --overwrite
    assert markers(tmp_path)["train"]["fingerprint"] == "f2"


def test_a_resume_may_change_only_what_it_extends(tmp_path):
    # train --epochs 6: fingerprint "e6" of all its settings, "kept" of all but --epochs
    prepare_output_dir(tmp_path, "train", "e6", resume_fingerprint="kept")
    (tmp_path / "metrics.jsonl").write_text("{}\n")
    assert markers(tmp_path)["train"] == {"command": "train", "fingerprint": "e6", "resume_fingerprint": "kept"}
    with pytest.raises(CrchflError, match="with other settings"):  # --epochs 10 without --resume: another setting
        prepare_output_dir(tmp_path, "train", "e10", resume_fingerprint="kept")
    with pytest.raises(CrchflError, match="with other settings"):  # --resume with another seed
        prepare_output_dir(tmp_path, "train", "e10-seed4", resume_fingerprint="kept-seed4", resuming=True)
    prepare_output_dir(tmp_path, "train", "e10", resume_fingerprint="kept", resuming=True)  # --resume --epochs 10
    assert markers(tmp_path)["train"]["fingerprint"] == "e10"  # the folder now holds (or will) ten epochs
    with pytest.raises(CrchflError, match="with other settings"):
        prepare_output_dir(tmp_path, "train", "e6", resume_fingerprint="kept")
    # a marker written before resume fingerprints existed: a resume needs all settings the same
    marker_path(tmp_path, "train").write_text(json.dumps({"command": "train", "fingerprint": "e6"}))
    with pytest.raises(CrchflError, match="with other settings"):
        prepare_output_dir(tmp_path, "train", "e10", resume_fingerprint="kept", resuming=True)
    prepare_output_dir(tmp_path, "train", "e6", resume_fingerprint="kept", resuming=True)


def test_a_refused_input_puts_back_the_marker_it_found(tmp_path):
    prepare_output_dir(tmp_path, "train", "e6", resume_fingerprint="kept")
    (tmp_path / "metrics.jsonl").write_text("{}\n")
    before = marker_path(tmp_path, "train").read_bytes()
    with pytest.raises(CrchflError):  # --resume --epochs 3, refused by the checkpoint's six epochs
        with output_dir(tmp_path, "train", "e3", resume_fingerprint="kept", resuming=True):
            assert markers(tmp_path)["train"]["fingerprint"] == "e3"
            raise CrchflError("holds 6 epochs already")
    assert marker_path(tmp_path, "train").read_bytes() == before
    with pytest.raises(RuntimeError):  # killed while extending: the marker names the settings being written
        with output_dir(tmp_path, "train", "e10", resume_fingerprint="kept", resuming=True):
            raise RuntimeError("killed half-way")
    assert markers(tmp_path)["train"]["fingerprint"] == "e10"


def test_files_without_a_marker_are_refused_unless_the_command_resumes_or_overwrites(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(CrchflError, match="already holds files that are not this command's results"):
        prepare_output_dir(tmp_path, "drive", "f")
    prepare_output_dir(tmp_path, "dataset", "f", resumable=True)  # the data set writer judges its own folder
    with pytest.raises(CrchflError, match="holds the results of `crchfl-sumo dataset`"):
        prepare_output_dir(tmp_path, "run", resumable=True)
    prepare_output_dir(tmp_path, "dataset-stats", "g", beside=("dataset",))  # statistics beside their data set
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_output_dir_takes_back_what_it_made_when_the_work_fails_before_writing(tmp_path):
    out = tmp_path / "new" / "out"
    with pytest.raises(CrchflError):
        with output_dir(out, "simulate", "f"):
            raise CrchflError("bad config")
    assert not (tmp_path / "new").exists()
    with pytest.raises(RuntimeError):
        with output_dir(out, "simulate", "f"):
            (out / "trace.csv").write_text("t_s\n")
            raise RuntimeError("killed half-way")
    assert (out / "trace.csv").exists() and markers(out)["simulate"]["fingerprint"] == "f"  # rerun with it


def test_check_writable(tmp_path):
    from crchfl_sumo.core.outputs import check_writable

    check_writable(tmp_path, "report x")
    with pytest.raises(CrchflError, match="report x: no such folder"):
        check_writable(tmp_path / "none", "report x")
    assert list(tmp_path.iterdir()) == []


def test_prepare_output_file(tmp_path):
    assert prepare_output_file(tmp_path / "sub" / "fig.png") == tmp_path / "sub" / "fig.png"
    assert (tmp_path / "sub").is_dir()
    with pytest.raises(CrchflError, match="is a folder; give the path of the file"):
        prepare_output_file(tmp_path)
    (tmp_path / "f").write_text("x")
    with pytest.raises(CrchflError, match="cannot create its folder"):
        prepare_output_file(tmp_path / "f" / "fig.png")


def test_fingerprint_covers_settings_and_file_bytes(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text("seed = 1\n")
    a = fingerprint({"seed": 1, "x": 2})
    assert a == fingerprint({"x": 2, "seed": 1})  # keys sorted
    assert a != fingerprint({"seed": 2, "x": 2})
    with_file = fingerprint({"seed": 1, "x": 2}, [config])
    config.write_text("seed = 2\n")
    assert with_file != fingerprint({"seed": 1, "x": 2}, [config])


def test_prepare_output_file_refuses_an_existing_file_unless_replace(tmp_path):
    path = tmp_path / "fig.png"
    path.write_bytes(b"old")
    with pytest.raises(CrchflError, match=r"drive-compare --out .*fig.png: the file exists; .*--overwrite"):
        prepare_output_file(path, "drive-compare --out")
    assert prepare_output_file(path, "drive-compare --out", replace=True) == path
    assert path.read_bytes() == b"old"  # checked, not touched: the command writes it atomically later
