"""AtomicFile: outputs appear under their name only when complete."""

import pytest

from evchain.io.atomic import AtomicFile, atomic_write_bytes


def test_commit_renames_abort_keeps_partial_and_removes_stale(tmp_path):
    out = AtomicFile(tmp_path / "sub" / "a.bin")
    out.write(b"12")
    out.file.write(b"34")
    assert not (tmp_path / "sub" / "a.bin").exists()
    out.commit()
    out.abort()  # after commit: nothing
    assert (tmp_path / "sub" / "a.bin").read_bytes() == b"1234"
    assert not (tmp_path / "sub" / "a.bin.partial").exists()

    out = AtomicFile(tmp_path / "sub" / "a.bin")  # a second run that fails
    out.write(b"5")
    out.abort()
    out.commit()  # after abort: nothing
    assert not (tmp_path / "sub" / "a.bin").exists()
    assert (tmp_path / "sub" / "a.bin.partial").read_bytes() == b"5"
    with pytest.raises(ValueError, match="no open file"):
        out.write(b"6")


def test_context_manager_commits_or_aborts(tmp_path):
    with AtomicFile(tmp_path / "ok.txt") as out:
        out.write(b"done")
    assert (tmp_path / "ok.txt").read_bytes() == b"done"
    (tmp_path / "bad.txt").write_bytes(b"stale output of an earlier run")
    with pytest.raises(RuntimeError), AtomicFile(tmp_path / "bad.txt") as out:
        out.write(b"half")
        raise RuntimeError("disk on fire")
    assert not (tmp_path / "bad.txt").exists()
    assert (tmp_path / "bad.txt.partial").read_bytes() == b"half"
    atomic_write_bytes(tmp_path / "c.bin", b"xyz")
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "bad.txt.partial", "c.bin", "ok.txt"]


def test_reserve_leaves_the_writing_to_a_library(tmp_path):
    out = AtomicFile.reserve(tmp_path / "movie.gif")
    assert out.tmp == tmp_path / "movie.gif.partial" and not out.tmp.exists()
    with pytest.raises(ValueError, match="no open file"):
        out.write(b"x")
    out.tmp.write_bytes(b"GIF89a")  # what the library writes
    out.commit()
    assert (tmp_path / "movie.gif").read_bytes() == b"GIF89a"

    folder = tmp_path / "bag.partial"
    folder.mkdir()
    out = AtomicFile.reserve(tmp_path / "bag", folder / "bag")
    (folder / "bag").mkdir()
    out.abort()  # a failed run: the partial folder stays
    assert (folder / "bag").is_dir() and not (tmp_path / "bag").exists()
