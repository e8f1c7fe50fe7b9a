"""Atomic file writes: write to a temporary file in the same folder, then ``os.replace``.

An interrupted write leaves the previous file (or nothing) in place, never half a file. The file
gets the permissions a plain ``open(path, "w")`` would give it: an existing file's mode is kept, a
new one gets ``0o666`` less the process's umask (``tempfile.mkstemp`` alone would leave ``0o600``,
unreadable to the other users and services of the machine that read our outputs).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable, Iterator


_UMASK_LOCK = threading.Lock()


def new_file_mode() -> int:
    """The permission bits ``open(path, "w")`` gives a new file: ``0o666`` less the umask."""
    with _UMASK_LOCK:  # os.umask can only be read by setting it
        umask = os.umask(0o022)
        os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path`` atomically, with
    ``path``'s permissions if it existed, else those of a new file (``new_file_mode``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        try:
            mode = path.stat().st_mode & 0o7777
        except FileNotFoundError:
            mode = new_file_mode()
        os.chmod(tmp_path, mode)  # the writer may have replaced the temporary file: set the mode last
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write(path: str | os.PathLike, writer: Callable[[Path], None]) -> None:
    """Call ``writer(tmp_path)`` and move the result to ``path`` atomically."""
    with atomic_path(path) as tmp:
        writer(tmp)


# --------------------------------------------------------------------------- leftovers, names, folders
#: Temporary files of ``atomic_path``: ``.<name>.<8 random chars>.tmp<suffix>``.
_TEMP_FILE = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9_]+)?$")
#: A name that may become a file name: letters, digits, '_', '-', '.', not starting with '.' or '-'.
_SAFE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files an interrupted ``atomic_path`` left in ``folder`` (not
    recursive; only regular files matching its naming pattern). Returns what was removed."""
    folder = Path(folder)
    removed = []
    if not folder.is_dir():
        return removed
    for p in folder.iterdir():
        if _TEMP_FILE.match(p.name) and p.is_file() and not p.is_symlink():
            p.unlink()
            removed.append(p)
    return removed


def check_file_name(name: str, what: str) -> str:
    """``name`` if it is safe as a single file-name component (see ``_SAFE_NAME``: no path
    separator, no '..', no leading dot), else ValueError naming ``what`` and the value."""
    if not isinstance(name, str) or not _SAFE_NAME.match(name) or ".." in name:
        raise ValueError(f"{what} {name!r} cannot be used in file names: use 1-128 letters, digits, '_', '-' or '.' "
                         "(not starting with '.' or '-', no '..', no path separators)")
    return name


def open_append_no_follow(path: str | os.PathLike):
    """Open ``path`` for appending text, refusing a symbolic link (which could point outside
    the folder): ValueError naming the file."""
    path = Path(path)
    if path.is_symlink():
        raise ValueError(f"{path} is a symbolic link; refusing to write through it (remove the link)")
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as exc:
        if path.is_symlink():
            raise ValueError(f"{path} is a symbolic link; refusing to write through it (remove the link)") from exc
        raise
    return os.fdopen(fd, "a")


def check_output_folder(path: str | os.PathLike, option: str) -> Path:
    """``path`` unless it exists as something other than a folder (ValueError naming ``option``)."""
    if not str(path).strip():
        raise ValueError(f"{option} must name a folder, got {str(path)!r}")
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{option} {path} exists and is not a folder")
    return path


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike, *, replaceable: Callable[[Path], bool], option: str = "--out") \
        -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``path``; on success it replaces ``path`` whole.

    A folder is either the previous complete result or the new complete one, never a mix: an
    interrupted run leaves ``.<name>.partial-*`` (and, if killed during the swap,
    ``.<name>.old-*``) beside it, which the next call removes. An existing non-empty ``path``
    is replaced only when ``replaceable(path)`` (e.g. it holds a previous result's marker
    file); otherwise ValueError naming ``option``, so a user's own folder is never moved.
    """
    path = Path(path)
    check_output_folder(path, option)
    if path.is_dir() and any(path.iterdir()) and not replaceable(path):
        raise ValueError(f"{option} {path} is a non-empty folder that this command did not write; "
                         "choose a new or empty folder")
    parent = path.parent
    parent.mkdir(parents=True, exist_ok=True)
    for stale in list(parent.glob(f".{path.name}.partial-*")) + list(parent.glob(f".{path.name}.old-*")):
        if stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-", dir=parent))
    try:
        yield tmp
        if path.exists():
            old = parent / f".{path.name}.old-{tmp.name.rsplit('-', 1)[-1]}"
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def check_no_symlinks(root: str | os.PathLike, *names: str) -> None:
    """ValueError naming the link if any of the folders/files ``names`` under ``root`` (or a
    folder between them and ``root``) is a symbolic link: writing through a link planted in an
    output folder could write outside it."""
    root = Path(root)
    for name in names:
        p = root / name
        while p != root and p != p.parent:
            if p.is_symlink():
                raise ValueError(f"{p} is a symbolic link; refusing to write through it (remove the link)")
            p = p.parent


def read_json(path: str | os.PathLike, what: str) -> Any:
    """The JSON value in ``path``. FileNotFoundError ("<what> <path> does not exist") when it is not
    a file; ValueError ("cannot read <what> <path>: <reason>") when it is unreadable or not JSON."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read {what} {path}: {exc}") from exc
