"""Files in and out (host-side): YAML mappings read with their keys checked, and outputs written atomically with
the user's umask, every file or none."""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any, TypeVar

from . import inputs
from .params import ParameterError

_PathT = TypeVar("_PathT", bound="str | os.PathLike[str]")  # a path of a caller's {path: data}


def read_yaml_mapping(
    path: Path, what: str, keys: Collection[str], error: type[Exception] = ParameterError
) -> dict[str, Any]:
    """A YAML file holding a mapping whose keys are among ``keys`` (empty file: ``{}``).

    Read with :func:`pusupu_jax.inputs.read_yaml` (size limit, UTF-8, no aliases, no duplicate
    keys); raises ``error`` with the path and one line saying what is wrong (an unknown key is
    called a ``what`` in the message).
    """
    data = inputs.read_yaml(path, "YAML file", error)
    return inputs.check_keys({} if data is None else data, str(path), keys, error, what=what)


def umask() -> int:
    """The process's file-creation mask (read without changing it where the OS allows)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_output(path: str | os.PathLike[str]) -> os.stat_result | None:
    """What stands at ``path``, an output about to be written: nothing (None) or a regular file (its ``lstat``).

    Anything else (a symlink, folder, FIFO, socket or device node) raises :class:`ParameterError` in one line and is
    left as it is: a rename over it would replace the node itself (as root, ``--plot /dev/null`` replaced the device
    with a PNG), and a symlink is not followed to whatever it names.
    """
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    except NotADirectoryError:
        raise ParameterError(
            f"{path}: expected a file in a folder, but {str(Path(path).parent)!r} is not a folder"
        ) from None
    if not stat.S_ISREG(st.st_mode):
        raise ParameterError(
            f"{path}: expected a regular file to write (or nothing), found "
            f"{inputs.file_kind(st.st_mode)}; left as it is"
        )
    return st


def check_writable(folder: str | os.PathLike[str], option: str) -> None:
    """A file made and removed in ``folder``, an output's folder, before any work: permission bits alone miss a
    read-only or special file system (``/proc``, as root).  :class:`ParameterError` naming ``option`` otherwise."""
    try:
        tempfile.NamedTemporaryFile(dir=folder, prefix=".pusupu-write-test.").close()
    except OSError as e:
        raise ParameterError(f"{option}: cannot write in {str(folder)!r} ({e.strerror})") from None


def check_output_folder(path: str | os.PathLike[str], option: str = "--out") -> None:
    """``OPTION DIR``: a folder to write in, there now or to be made under its nearest existing parent, which must
    be a folder to write in; checked before any work, nothing made."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise ParameterError(f"{option}: expected a folder, got the file {str(path)!r}")
    base = os.path.abspath(path)
    while not os.path.exists(base):
        base = os.path.dirname(base)
    if not os.path.isdir(base):
        raise ParameterError(f"{option}: cannot write in {str(path)!r}: {base!r} above it is a file, not a folder")
    check_writable(base, option)


def write_files(files: Mapping[_PathT, str | bytes]) -> list[Path]:
    """Write ``{path: data}`` (str or bytes) atomically, every file or none as far as the file system allows.

    Every path is checked first (:func:`check_output`); then each file's data goes to a temporary file in its
    folder, synced; then, every path checked again, each temporary is renamed over its path.  A reader sees an old
    file or a new one, never a part; a failure before the renames (a full disk included) leaves every old file and no
    temporary behind.  A new file gets the mode a plain ``open`` would give it (``0666`` less the umask: ``0644``
    under the usual ``022``); a file written again keeps its permission bits (not a set-user or set-group ID) and,
    where the process may give it away (root), its owner and group.
    """
    items = [(Path(path), data.encode() if isinstance(data, str) else data) for path, data in files.items()]
    temps: list[str] = []
    try:
        for path, data in items:
            old = check_output(path)
            try:
                fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
            except OSError as e:  # named by the file asked for, not by the temporary that could not be made
                raise OSError(e.errno, f"cannot write a file in its folder ({e.strerror})", str(path)) from None
            temps.append(tmp)
            with os.fdopen(fd, "wb") as f:
                if old is not None and (old.st_uid, old.st_gid) != (os.geteuid(), os.getegid()):
                    with contextlib.suppress(PermissionError):  # only root may give a file away
                        os.fchown(fd, old.st_uid, old.st_gid)
                os.fchmod(fd, 0o666 & ~umask() if old is None else stat.S_IMODE(old.st_mode) & 0o777)
                f.write(data)
                f.flush()
                os.fsync(fd)
        for path, _ in items:
            check_output(path)
        for (path, _), tmp in zip(items, temps):
            os.replace(tmp, path)
    finally:
        for tmp in temps:
            if os.path.exists(tmp):
                os.unlink(tmp)
    return [path for path, _ in items]


def write_atomic(path: str | os.PathLike[str], data: str | bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`write_files`: a regular file or nothing at ``path``, its mode
    kept)."""
    return write_files({path: data})[0]
