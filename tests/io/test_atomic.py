import errno
import os
import stat

import pytest

import gridmerge.io.atomic as atomic_module
from gridmerge.errors import GridMergeError, OutputError
from gridmerge.io import atomic_files, atomic_write


def names(folder):
    return sorted(p.name for p in folder.iterdir())


def fail_on_call(monkeypatch, n):
    """Make the n-th call of os.replace (1-based) fail with EIO; return the call log."""
    real_replace = os.replace
    calls = []

    def fake_replace(src, dst, *args, **kwargs):
        calls.append((os.fspath(src), os.fspath(dst)))
        if len(calls) == n:
            raise OSError(errno.EIO, "simulated I/O error")
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(atomic_module.os, "replace", fake_replace)
    return calls


def test_atomic_write_creates_file_without_leftovers(tmp_path):
    target = tmp_path / "out.bin"
    assert atomic_write(target, b"\x00\x01data") == target
    assert target.read_bytes() == b"\x00\x01data"
    assert names(tmp_path) == ["out.bin"]


def test_atomic_write_accepts_str_path_and_bytes_like(tmp_path):
    atomic_write(str(tmp_path / "a"), bytearray(b"abc"))
    atomic_write(tmp_path / "b", memoryview(b"xyz"))
    assert (tmp_path / "a").read_bytes() == b"abc"
    assert (tmp_path / "b").read_bytes() == b"xyz"


def test_atomic_write_replaces_existing_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_bytes(b"old content that is longer")
    atomic_write(target, b"new")
    assert target.read_bytes() == b"new"
    assert names(tmp_path) == ["out.txt"]


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_atomic_write_keeps_permissions_of_replaced_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_bytes(b"old")
    os.chmod(target, 0o600)
    atomic_write(target, b"new")
    assert stat.S_IMODE(os.stat(target).st_mode) == 0o600


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_new_file_gets_umask_permissions_not_private_temp_ones(tmp_path):
    old_umask = os.umask(0o022)
    try:
        atomic_write(tmp_path / "out.txt", b"x")
    finally:
        os.umask(old_umask)
    assert stat.S_IMODE(os.stat(tmp_path / "out.txt").st_mode) == 0o644


def test_missing_folder_raises_output_error_naming_it(tmp_path):
    folder = tmp_path / "no" / "such"
    with pytest.raises(OutputError) as excinfo:
        atomic_write(folder / "out.txt", b"x")
    message = str(excinfo.value)
    assert str(folder) in message
    assert "\n" not in message
    assert isinstance(excinfo.value, OSError)
    assert isinstance(excinfo.value, GridMergeError)
    assert names(tmp_path) == []


def test_target_that_is_a_directory_raises_output_error(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(OutputError, match="directory"):
        atomic_write(tmp_path / "d", b"x")
    assert names(tmp_path) == ["d"]


def test_several_files_appear_together(tmp_path):
    with atomic_files() as out:
        out.write(tmp_path / "map.yaml", b"yaml")
        out.write(tmp_path / "map.pgm", b"pgm")
        # Nothing is visible under the final names before the block ends.
        assert not (tmp_path / "map.yaml").exists()
        assert not (tmp_path / "map.pgm").exists()
        temporaries = names(tmp_path)
        assert len(temporaries) == 2
        assert all(n.startswith((".map.yaml.tmp-", ".map.pgm.tmp-")) for n in temporaries)
        assert out.targets == [tmp_path / "map.yaml", tmp_path / "map.pgm"]
    assert names(tmp_path) == ["map.pgm", "map.yaml"]
    assert (tmp_path / "map.yaml").read_bytes() == b"yaml"
    assert (tmp_path / "map.pgm").read_bytes() == b"pgm"


class FailingSerialiser:
    def __bytes__(self):
        raise RuntimeError("cannot serialise")


def test_exception_during_serialisation_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="cannot serialise"):
        with atomic_files() as out:
            out.write(tmp_path / "map.yaml", b"yaml")
            out.write(tmp_path / "map.pgm", bytes(FailingSerialiser()))
    assert names(tmp_path) == []


def test_exception_during_serialisation_keeps_existing_targets(tmp_path):
    (tmp_path / "map.yaml").write_bytes(b"old yaml")
    (tmp_path / "map.pgm").write_bytes(b"old pgm")
    with pytest.raises(RuntimeError):
        with atomic_files() as out:
            out.write(tmp_path / "map.yaml", b"new yaml")
            out.write(tmp_path / "map.pgm", bytes(FailingSerialiser()))
    assert names(tmp_path) == ["map.pgm", "map.yaml"]
    assert (tmp_path / "map.yaml").read_bytes() == b"old yaml"
    assert (tmp_path / "map.pgm").read_bytes() == b"old pgm"


def test_missing_folder_of_second_file_discards_the_first(tmp_path):
    with pytest.raises(OutputError) as excinfo:
        with atomic_files() as out:
            out.write(tmp_path / "map.yaml", b"yaml")
            out.write(tmp_path / "missing" / "map.pgm", b"pgm")
    assert str(tmp_path / "missing") in str(excinfo.value)
    assert names(tmp_path) == []


def test_failed_rename_of_second_file_creates_nothing(tmp_path, monkeypatch):
    calls = fail_on_call(monkeypatch, 2)
    with pytest.raises(OutputError, match="simulated I/O error") as excinfo:
        with atomic_files() as out:
            out.write(tmp_path / "map.yaml", b"yaml")
            out.write(tmp_path / "map.pgm", b"pgm")
    assert len(calls) == 2
    assert str(tmp_path / "map.pgm") in str(excinfo.value)  # names the file that failed
    assert names(tmp_path) == []


def test_failed_rename_of_second_file_restores_first_target(tmp_path, monkeypatch):
    (tmp_path / "map.yaml").write_bytes(b"old yaml")
    (tmp_path / "map.pgm").write_bytes(b"old pgm")
    calls = fail_on_call(monkeypatch, 2)
    with pytest.raises(OutputError):
        with atomic_files() as out:
            out.write(tmp_path / "map.yaml", b"new yaml")
            out.write(tmp_path / "map.pgm", b"new pgm")
    assert len(calls) >= 2  # the first rename happened and was undone
    assert names(tmp_path) == ["map.pgm", "map.yaml"]
    assert (tmp_path / "map.yaml").read_bytes() == b"old yaml"
    assert (tmp_path / "map.pgm").read_bytes() == b"old pgm"


def test_failed_single_write_keeps_old_file(tmp_path, monkeypatch):
    target = tmp_path / "out.txt"
    target.write_bytes(b"old")
    fail_on_call(monkeypatch, 1)
    with pytest.raises(OutputError):
        atomic_write(target, b"new")
    assert target.read_bytes() == b"old"
    assert names(tmp_path) == ["out.txt"]


def test_same_target_twice_is_refused(tmp_path):
    with pytest.raises(ValueError, match="twice"):
        with atomic_files() as out:
            out.write(tmp_path / "a.txt", b"1")
            out.write(tmp_path / "." / "a.txt", b"2")
    assert names(tmp_path) == []


def test_keyboard_interrupt_discards_batch(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with atomic_files() as out:
            out.write(tmp_path / "a.txt", b"1")
            raise KeyboardInterrupt
    assert names(tmp_path) == []
