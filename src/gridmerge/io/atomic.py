"""All-or-nothing file output.

A map is a pair of files (a YAML and its image); a reader must never find one of them new
and the other old, half written, or missing because gridmerge failed half way. Every
output therefore goes through :func:`atomic_files`: each file is first written in full to
a hidden temporary file next to its target (``.NAME.tmp-PID-N``), flushed and fsync'ed,
and only when every file of the batch has been written are they renamed over their
targets with :func:`os.replace`. If anything fails, the temporary files are removed and
every target is left as it was (or absent, if it did not exist).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import stat
from pathlib import Path
from typing import Iterator, Union

from ..errors import OutputError

__all__ = ["atomic_write", "atomic_files", "AtomicFiles"]

PathLike = Union[str, "os.PathLike[str]"]

# Temporary names are made unique with the process id and a counter (and O_EXCL), so no
# randomness is involved.
_counter = itertools.count()


def _check_folder(target: Path) -> None:
    folder = target.parent
    if not folder.is_dir():
        raise OutputError(f"output folder does not exist: {folder}")
    if target.is_dir():
        raise OutputError(f"output path is a directory: {target}")


def _sibling(target: Path, kind: str) -> Path:
    """A new hidden name next to ``target``: ``.NAME.KIND-PID-N``."""
    return target.with_name(f".{target.name}.{kind}-{os.getpid()}-{next(_counter)}")


def _create_sibling(target: Path, kind: str) -> tuple[Path, int]:
    """Create and open (for writing) a new, empty hidden file next to ``target``."""
    while True:
        candidate = _sibling(target, kind)
        try:
            # 0o666 lets the umask decide the permissions, as for a plain open().
            fd = os.open(candidate, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
        except FileExistsError:
            continue
        return candidate, fd


def _backup(target: Path) -> Path:
    """Keep the current content of ``target`` under a hidden name, to restore it on failure."""
    while True:
        candidate = _sibling(target, "bak")
        try:
            os.link(target, candidate)  # cheap: a second name for the same file
            return candidate
        except FileExistsError:
            continue
        except OSError:
            break  # no hard links on this file system: copy instead
    candidate, fd = _create_sibling(target, "bak")
    os.close(fd)
    try:
        shutil.copy2(target, candidate)
    except BaseException:
        _remove_quietly(candidate)
        raise
    return candidate


def _remove_quietly(path: Path) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


def _fsync_folder(folder: Path) -> None:
    """Make the renames in ``folder`` durable (POSIX only; best effort)."""
    if os.name != "posix":
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class AtomicFiles:
    """A batch of files that replace their targets together; made by :func:`atomic_files`."""

    def __init__(self) -> None:
        self._staged: list[tuple[Path, Path]] = []  # (temporary, target)

    @property
    def targets(self) -> list[Path]:
        """The targets written so far, in order."""
        return [target for _, target in self._staged]

    def write(self, path: PathLike, data: bytes | bytearray | memoryview) -> Path:
        """Write ``data`` to a temporary file that will replace ``path`` on commit.

        Parameters
        ----------
        path : str or path-like
            The target file. Its folder must exist.
        data : bytes-like
            The complete content of the file.

        Returns
        -------
        pathlib.Path
            The target path.

        Raises
        ------
        OutputError
            The target's folder does not exist, the target is a folder, or the temporary
            file cannot be written (permission denied, disk full, ...).
        ValueError
            The same target was already written in this batch.
        """
        target = Path(path)
        _check_folder(target)
        if any(os.path.abspath(target) == os.path.abspath(t) for _, t in self._staged):
            raise ValueError(f"{target} is written twice in one batch")
        try:
            tmp, fd = _create_sibling(target, "tmp")
        except OSError as exc:
            raise OutputError(f"cannot create a file in {target.parent}: {exc.strerror or exc}") from None
        self._staged.append((tmp, target))
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            if target.exists():
                # Keep the permissions of the file being replaced, as an in-place write would.
                os.chmod(tmp, stat.S_IMODE(os.stat(target).st_mode))
        except OSError as exc:
            raise OutputError(f"cannot write {target}: {exc.strerror or exc}") from None
        return target

    # ----------------------------------------------------------------- internals
    def _discard(self) -> None:
        for tmp, _ in self._staged:
            _remove_quietly(tmp)
        self._staged.clear()

    def _commit(self) -> None:
        """Rename every temporary file over its target, undoing all renames on failure."""
        done: list[tuple[Path, Path | None]] = []  # (target, backup of its old content)
        backups: list[Path] = []
        try:
            for tmp, target in self._staged:
                backup = None
                if target.exists():
                    backup = _backup(target)
                    backups.append(backup)
                os.replace(tmp, target)
                done.append((target, backup))
        except BaseException as exc:
            failed = target
            for done_target, backup in reversed(done):
                with contextlib.suppress(OSError):
                    if backup is None:
                        os.unlink(done_target)
                    else:
                        os.replace(backup, done_target)
            self._discard()
            for backup in backups:
                _remove_quietly(backup)
            if isinstance(exc, OSError) and not isinstance(exc, OutputError):
                raise OutputError(f"cannot replace {failed}: {exc.strerror or exc}") from exc
            raise
        for backup in backups:
            _remove_quietly(backup)
        self._staged.clear()
        for folder in sorted({target.parent for target, _ in done}):
            _fsync_folder(folder)


@contextlib.contextmanager
def atomic_files() -> Iterator[AtomicFiles]:
    """Write several files so that they all appear together, or none does.

    Yields an :class:`AtomicFiles` whose :meth:`~AtomicFiles.write` stages one file. When
    the ``with`` block ends normally every staged file replaces its target; if the block
    raises, the staged files are deleted and no target is created or modified.

    Raises
    ------
    OutputError
        A target's folder does not exist (raised by ``write``, before anything is
        written), or a file cannot be written or renamed.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> tmp = tempfile.TemporaryDirectory()
    >>> folder = pathlib.Path(tmp.name)
    >>> with atomic_files() as out:
    ...     _ = out.write(folder / "map.yaml", b"image: map.pgm\\n")
    ...     _ = out.write(folder / "map.pgm", b"P5\\n1 1\\n255\\n\\xfe")
    >>> sorted(p.name for p in folder.iterdir())
    ['map.pgm', 'map.yaml']
    >>> try:
    ...     with atomic_files() as out:
    ...         _ = out.write(folder / "other.yaml", b"x: 1\\n")
    ...         raise RuntimeError("serialisation failed")
    ... except RuntimeError:
    ...     pass
    >>> sorted(p.name for p in folder.iterdir())
    ['map.pgm', 'map.yaml']
    >>> tmp.cleanup()
    """
    batch = AtomicFiles()
    try:
        yield batch
    except BaseException:
        batch._discard()
        raise
    batch._commit()


def atomic_write(path: PathLike, data: bytes | bytearray | memoryview) -> Path:
    """Replace (or create) the file ``path`` with ``data`` atomically.

    The data goes to a temporary file in the same folder, which is fsync'ed and then
    renamed over ``path``: readers see either the old file or the complete new one.

    Parameters
    ----------
    path : str or path-like
        The target file; its folder must exist.
    data : bytes-like
        The complete new content.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    OutputError
        The folder does not exist or the file cannot be written.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> tmp = tempfile.TemporaryDirectory()
    >>> target = pathlib.Path(tmp.name) / "hello.txt"
    >>> atomic_write(target, b"hello") == target
    True
    >>> target.read_bytes()
    b'hello'
    >>> tmp.cleanup()
    """
    with atomic_files() as batch:
        target = batch.write(path, data)
    return target
