import pytest

from crchfl_sumo.core.atomic import atomic_path, atomic_write_text


def test_write_replaces_whole_file(tmp_path):
    target = tmp_path / "sub" / "a.txt"
    atomic_write_text(target, "first")
    atomic_write_text(target, "second")
    assert target.read_text() == "second"
    assert [p.name for p in target.parent.iterdir()] == ["a.txt"]  # no temporary left behind


def test_failure_midway_keeps_the_old_file(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_keeping_previous_renames_the_replaced_file_aside_and_read_latest_falls_back_to_it(tmp_path):
    from crchfl_sumo.core.atomic import atomic_path_keeping_previous, previous_path, read_latest
    from crchfl_sumo.core.errors import CrchflError

    path = tmp_path / "checkpoint.pt"
    assert previous_path(path) == tmp_path / "checkpoint.prev.pt"
    for text in ("one", "two", "three"):
        with atomic_path_keeping_previous(path) as tmp:
            tmp.write_text(text)
    assert path.read_text() == "three" and previous_path(path).read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.prev.pt", "checkpoint.pt"]

    def read(p):
        text = p.read_text() if p.is_file() else ""
        if not text.isalpha():
            raise CrchflError(f"{p}: damaged")
        return text

    assert read_latest(path, read, "checkpoint", "start afresh") == ("three", path)
    path.write_text("thr\0")
    assert read_latest(path, read, "checkpoint", "start afresh") == ("two", previous_path(path))
    # the damaged file is gone, so the next save cannot rename it over the good previous copy
    assert not path.exists()
    with atomic_path_keeping_previous(path) as tmp:
        tmp.write_text("four")
    assert path.read_text() == "four" and previous_path(path).read_text() == "two"
    path.unlink()  # killed between the two renames
    assert read_latest(path, read, "checkpoint", "start afresh") == ("two", previous_path(path))
    previous_path(path).write_text("")
    with pytest.raises(CrchflError, match=r"checkpoint.pt: damaged; the previous checkpoint is no better "
                                          r"\(.*checkpoint.prev.pt: damaged\); start afresh"):
        read_latest(path, read, "checkpoint", "start afresh")
    previous_path(path).unlink()
    with pytest.raises(CrchflError, match=r"checkpoint.pt: damaged$"):  # no previous copy: the latest's reason
        read_latest(path, read, "checkpoint", "start afresh")
