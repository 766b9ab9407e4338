"""Writing an output file without ever destroying anything: an output that resolves to an
input is refused (:func:`same_file`), whether it can be written is tried before the work
starts (:func:`cannot_create_in`), and the file is written beside its place under a
temporary name and renamed over it only when complete (:func:`replaced_when_done`), so a
failure (a full disk, an interrupt, an error halfway) leaves what was there before and no
half file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path


def same_file(out: str | Path, inputs: Iterable[str | Path | None]) -> Path | None:
    """The first of ``inputs`` that ``out`` would overwrite: the same path once links and
    ``..`` are resolved, or the same file by another name (a hard link); else ``None``."""
    out = Path(out)
    target = out.resolve()
    for given in inputs:
        if given is None:
            continue
        p = Path(given)
        if p.resolve() == target:
            return p
        with contextlib.suppress(OSError):
            if out.exists() and p.exists() and os.path.samefile(out, p):
                return p
    return None


def cannot_create_in(path: str | Path) -> str | None:
    """Why no file can be created where ``path`` would be (tried: a file made and removed in
    the nearest existing directory on its way, ``path``'s own when it exists), or ``None``.

    A permission check alone says yes to root on a read-only or virtual file system
    (``/sys``, ``/proc``); this tries what the write will do.
    """
    path = Path(path)
    here = path.parent if str(path.parent) else Path(".")
    while not here.exists() and here != here.parent:
        here = here.parent
    if not here.is_dir():
        return f"{here} is a file, not a directory"
    try:
        fd, probe = tempfile.mkstemp(prefix=".armfusion-probe-", dir=here)
    except OSError as e:
        return f"cannot create files in {here} ({e.strerror or e})"
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)
    if path.exists() and not os.access(path, os.W_OK):
        return "cannot be replaced (no permission)"
    return None


@contextlib.contextmanager
def replaced_when_done(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to (its missing directories made); renamed
    over ``path`` when the block ends without an exception (and flushed to disk first),
    removed when it raises."""
    path = Path(path)
    # (a missing directory on the way is made, as :func:`cannot_create_in` found it can be:
    # a run's output was lost at its end on "No such file or directory")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent or ".")
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, _mode_for(path))  # (mkstemp's file is the owner's alone)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _mode_for(path: Path) -> int:
    """The permissions ``path`` has, or a new file gets (0o666 less the umask)."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def write_text_replacing(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` by :func:`replaced_when_done`."""
    with replaced_when_done(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
