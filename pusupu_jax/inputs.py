"""Reading what users and other programs hand us (host-side): one place for every loader's checks.

* :func:`read_bytes`: a regular file of at most a given size, opened without blocking: a folder,
  FIFO, socket or device given as an input is refused before it is opened (a FIFO would block
  the read forever, a device can be endless or act when opened);
* :func:`read_yaml`: a file of at most :data:`MAX_FILE_BYTES`, in UTF-8, parsed as YAML with no
  aliases or anchors (a few hundred bytes of nested aliases expand to gigabytes) and no
  duplicate keys, whose mappings have string keys;
* :func:`check_keys`: a mapping whose keys are known (and include the required ones);
* :func:`number`, :func:`integer`, :func:`choice`: one value of the expected kind.

Every failure raises the caller's error class (a :class:`~pusupu_jax.params.ParameterError`)
with one line: where, what was expected, what was found.  A value echoed back is cut to
:data:`MAX_SHOWN` characters and escaped (:func:`shown`); :func:`one_line` makes any message one
printable line (the ``pusupu`` command prints its errors through it).

What YAML users write and is accepted: an integer where a real is expected (``5`` for ``5.0``),
exponents (``1.0e-3``), YAML 1.1 integers in hex or octal (``0x10``), ``null`` where a key says
it may be null.  What is refused: quoted numbers (``"0.015"``: a string), booleans where numbers
are expected (``true`` is not 1), ``.nan`` and ``.inf`` (unless a key says so), duplicate keys,
aliases and anchors, keys that are not strings (``{1: 2}``).
"""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

MAX_FILE_BYTES = 1 << 20  # 1 MiB: a parameter, gain, configuration or job file is a few kB
MAX_SHOWN = 200  # characters of a value echoed in an error (a 500 kB value is not printed back)
MAX_LINE = 1000  # characters of a whole error line


class _Strict(yaml.SafeLoader):  # type: ignore[misc]  # PyYAML ships no type stubs: its classes are Any
    """SafeLoader without aliases or anchors, without duplicate keys, with string keys only."""

    def compose_node(self, parent: yaml.Node | None, index: object) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            raise yaml.YAMLError(f"aliases are not accepted (line {self.peek_event().start_mark.line + 1})")
        event = self.peek_event()
        if getattr(event, "anchor", None) is not None:
            raise yaml.YAMLError(f"anchors are not accepted (line {event.start_mark.line + 1})")
        return super().compose_node(parent, index)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[str] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, str):
                raise yaml.YAMLError(f"expected string keys, got {shown(key)} (line {key_node.start_mark.line + 1})")
            if key in seen:
                raise yaml.YAMLError(f"duplicate key {shown(key)} (line {key_node.start_mark.line + 1})")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)  # type: ignore[no-any-return]  # PyYAML ships no type stubs


def parse_yaml(text: str, where: str, error: type[Exception]) -> Any:
    """``text`` parsed with the strict loader; ``error(f"{where}: ...")`` when it is not such YAML."""
    try:
        return yaml.load(text, Loader=_Strict)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as e:
        raise error(f"{where}: not valid YAML ({str(e).splitlines()[0]})") from None
    except RecursionError:
        raise error(f"{where}: not valid YAML (nested too deeply)") from None
    except ValueError as e:  # a value Python refuses to build: an integer of more than 4300 digits
        raise error(f"{where}: not valid YAML ({str(e).split(': ')[0]})") from None


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, as errors name it: 'a regular file', 'a folder', 'a FIFO', ..."""
    for test, name in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISLNK, "a symlink"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    ):
        if test(mode):
            return name
    return "a special file"


def read_bytes(path: str | os.PathLike[str], what: str, error: type[Exception], limit: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of the regular file ``path`` (a symlink to one is followed), at most ``limit`` bytes.

    Anything else is refused before it is opened; the file is then opened without blocking and
    checked again (``fstat``), so that a FIFO or device put in its place meanwhile is refused too,
    and its size is checked before it is read.  ``what`` names the file in errors.
    """
    path = Path(path)

    def regular(mode: int) -> None:
        if not stat.S_ISREG(mode):
            raise error(f"{path}: expected a {what}, got {file_kind(mode)}")

    try:
        regular(os.stat(path).st_mode)
        with os.fdopen(os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC), "rb") as f:
            st = os.fstat(f.fileno())
            regular(st.st_mode)
            size = st.st_size
            data = f.read(limit + 1) if size <= limit else b""
    except OSError as e:
        raise error(f"{path}: cannot read {what} ({e.strerror})") from None
    if size > limit or len(data) > limit:
        raise error(f"{path}: expected a {what} of at most {limit / 1024:.0f} KiB, got a larger file")
    return data


def read_text(path: str | os.PathLike[str], what: str, error: type[Exception]) -> str:
    """The UTF-8 text of a regular file of at most :data:`MAX_FILE_BYTES` (:func:`read_bytes`; ``what`` names it in
    errors)."""
    data = read_bytes(path, what, error)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(
            f"{Path(path)}: expected a UTF-8 text {what}, found a byte 0x{data[e.start]:02x} at {e.start} "
            "that is not UTF-8"
        ) from None


def read_yaml(path: str | os.PathLike[str], what: str, error: type[Exception]) -> Any:
    """A YAML file, read with :func:`read_text` and parsed with :func:`parse_yaml`."""
    return parse_yaml(read_text(path, what, error), str(path), error)


def check_keys(
    value: object,
    where: str,
    known: Collection[str],
    error: type[Exception],
    required: Collection[str] = (),
    what: str = "key",
) -> dict[str, Any]:
    """``value`` as a mapping whose keys are among ``known`` and include ``required``."""
    if not isinstance(value, dict):
        raise error(f"{where}: expected a mapping of {what}s, got {_kind(value)}")
    bad = [k for k in value if not isinstance(k, str)]
    if bad:
        raise error(f"{where}: expected string keys, got {shown(bad[0])}")
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise error(f"{where}: unknown {what} {shown(unknown[0])}; expected some of {sorted(known)}")
    missing = [k for k in required if k not in value]
    if missing:
        raise error(f"{where}: missing {what} {missing[0]!r}")
    return value


def number(
    value: object,
    where: str,
    error: type[Exception],
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    finite: bool = True,
) -> float:
    """A real number (an int or a float; not a bool, not a string) within ``[low, high]`` (``(low, ...`` if
    ``low_open``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(f"{where}: expected a number, got {_kind(value)}")
    v = float(value)
    if finite and not math.isfinite(v):
        raise error(f"{where}: expected a finite number, got {v}")
    if math.isnan(v):
        raise error(f"{where}: expected a number, got nan")
    if low is not None and (v < low or (low_open and v == low)):
        raise error(f"{where}: expected a number {'>' if low_open else '>='} {low:g}, got {v:g}")
    if high is not None and v > high:
        raise error(f"{where}: expected a number <= {high:g}, got {v:g}")
    return v


def integer(
    value: object, where: str, error: type[Exception], *, low: int | None = None, high: int | None = None
) -> int:
    """An integer (not a bool, not a float) within ``[low, high]``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise error(f"{where}: expected an integer, got {_kind(value)}")
    if (low is not None and value < low) or (high is not None and value > high):
        span = f"in [{low}, {high}]" if high is not None else f">= {low}"
        raise error(f"{where}: expected an integer {span}, got {value}")
    return value


def array(value: object, where: str, shape: Sequence[int], error: type[Exception]) -> npt.NDArray[np.float64]:
    """``value`` as a float64 numpy array of ``shape``, every element finite."""
    import numpy as np

    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise error(f"{where}: expected numbers of shape {shape}, got {shown(value)}") from None
    if arr.shape != tuple(shape):
        raise error(f"{where}: expected shape {tuple(shape)}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise error(f"{where}: expected finite numbers, got {arr[~np.isfinite(arr)].flat[0]}")
    return arr


def choice(value: object, where: str, choices: Collection[str], error: type[Exception]) -> str:
    """One of ``choices`` (strings)."""
    if not isinstance(value, str) or value not in choices:
        raise error(f"{where}: expected one of {tuple(map(str, choices))}, got {shown(value)}")
    return value


def _kind(value: object) -> str:
    """How an unexpected value is named in errors: its repr when short, else its type."""
    text = repr(value)
    return f"{type(value).__name__} {text}" if len(text) <= 40 else f"a {type(value).__name__}"


def shown(value: object, limit: int = MAX_SHOWN) -> str:
    """``value`` as an error echoes it: its repr (quoted, newlines and control characters escaped), cut to ``limit``
    characters."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def one_line(message: str, limit: int = MAX_LINE) -> str:
    """``message`` as one printable line of at most about ``limit`` characters: newlines, control and other
    non-printable characters escaped as in a repr, the rest cut."""
    cut = message[:limit]
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in cut)[:limit]
    return text if len(message) <= limit and len(text) <= limit else f"{text}... ({len(message)} characters)"
