"""Tuning checkpoints: the optimiser's state written atomically every few iterations, and read back only when it
is exactly what this run would write (its digest, layout, sizes and dtypes; never unpickled)."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import zipfile
import zlib
from pathlib import Path

import jax
import numpy as np

from pusupu_jax import inputs
from pusupu_jax.files import write_atomic
from pusupu_jax.inputs import shown
from pusupu_jax.params import ParameterError

from .state import Evaluation, TunerState

CHECKPOINT, CHECKPOINT_FORMAT = "checkpoint.npz", "pusupu-checkpoint-2"
META = ("format", "digest", "start", "iteration", "history", "best_value", "failed", "done")  # meta's keys


def save_checkpoint(path: Path, state: TunerState) -> None:
    """The optimiser state (:class:`pusupu_jax.tune.state.TunerState`) as one ``.npz`` of arrays (``z/<field>``,
    ``best/<field>``, ``opt/<k>``: the optax state's leaves in order) plus its JSON ``meta`` (digest, counters,
    histories, best values, failed members), written atomically."""
    arrays = {f"z/{k}": np.asarray(v) for k, v in (state.z or {}).items()}
    arrays |= {f"best/{k}": np.asarray(v) for k, v in state.best_z.items()}
    if state.opt is not None:
        arrays |= {f"opt/{k}": np.asarray(leaf) for k, leaf in enumerate(jax.tree.leaves(state.opt))}
    meta = {
        "format": CHECKPOINT_FORMAT,
        "digest": state.digest,
        "start": state.start,
        "iteration": state.iteration,
        "history": [[h.to_json() for h in history] for history in state.history],
        "best_value": np.asarray(state.best_value, dtype=float).tolist(),
        "failed": {str(m): message for m, message in state.failed.items()},
        "done": state.done,
    }
    buffer = io.BytesIO()
    np.savez(buffer, meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
    write_atomic(path, buffer.getvalue())


NPY_HEADER = 4096  # bytes: at most an array's .npy header in a checkpoint (numpy writes 128)
ZIP_RECORD = 1024  # bytes: at most a member's records in the zip (local and central headers, name, zip64 fields)
# what reading a crafted zip, .npy or JSON raises (ValueError covers JSON's and UTF-8's errors; RecursionError: nesting)
CHECKPOINT_ERRORS = (
    OSError,
    ValueError,
    OverflowError,  # a number too large for a float (JSON's integers have no bound)
    KeyError,
    EOFError,
    NotImplementedError,
    RecursionError,
    zipfile.BadZipFile,
    zlib.error,
)


@dataclasses.dataclass(frozen=True)
class CheckpointLayout:
    """What a checkpoint of one optimisation may hold, from its settings: :func:`load_checkpoint` checks a file against
    it before it loads any array.

    ``z``: the members' log-parameters ``{field: array}`` (a leading member axis), whose shapes and dtypes
    ``z/<field>`` and ``best/<field>`` have; ``opt``: an optax state of the right structure, whose leaves ``opt/<k>``
    are; ``iterations``, ``starts``: each start evaluates ``iterations + 1`` points, one history entry each;
    ``members``: the number of members (a history, a best value and perhaps a failure each); ``sequential``: the
    starts run one after another in each member (a single problem), not as members of their own (a batch).
    """

    z: dict
    opt: object
    iterations: int
    starts: int = 1
    members: int = 1
    sequential: bool = True

    def arrays(self) -> dict:
        """``{name: (shape, dtype)}`` of every array but ``meta`` that a checkpoint may hold."""
        out = {f"{group}/{k}": (np.shape(v), np.asarray(v).dtype) for group in ("z", "best") for k, v in self.z.items()}
        return out | {
            f"opt/{k}": (np.shape(leaf), np.asarray(leaf).dtype) for k, leaf in enumerate(jax.tree.leaves(self.opt))
        }

    def entries(self) -> int:
        """History entries of one history (a member's in a batch) at most."""
        return (self.iterations + 1) * (self.starts if self.sequential else 1)

    def meta_bytes(self) -> int:
        """At most the JSON ``meta`` [bytes]: every history entry with its ``z`` (32 characters a number), a best value
        and a failure message per member."""
        values = sum(np.size(v) for v in self.z.values()) // self.members
        return 4096 + self.members * (self.entries() * (256 + 32 * (values + len(self.z))) + 256)

    def file_bytes(self) -> int:
        """At most the whole file [bytes]: ``meta`` and every array, with their headers and records in the zip."""
        arrays = [int(np.prod(shape)) * dtype.itemsize for shape, dtype in self.arrays().values()]
        return self.meta_bytes() + sum(arrays) + (len(arrays) + 1) * (NPY_HEADER + ZIP_RECORD) + ZIP_RECORD


def _array_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int) -> tuple:
    """``(shape, dtype)`` of the array in member ``info``, from its declared size (at most ``limit`` bytes of data) and
    its .npy header alone: nothing else of it is decompressed."""
    if info.file_size > limit + NPY_HEADER:
        raise ValueError(
            f"{shown(info.filename)} declares {info.file_size} bytes, expected at most {limit + NPY_HEADER}"
        )
    with zf.open(info) as f:
        version = np.lib.format.read_magic(f)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f"{shown(info.filename)}: .npy version {version}, expected 1.0 or 2.0")
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(f)
    if dtype.hasobject:
        raise ValueError(f"{shown(info.filename)}: an object array, expected numbers")
    return shape, dtype


def _check_meta(meta: dict, layout: CheckpointLayout) -> None:
    """The JSON ``meta`` of a checkpoint of ``layout``'s settings: its keys, counters and history entries."""
    inputs.check_keys(meta, "meta", META, ValueError, required=META)
    inputs.integer(meta["start"], "meta.start", ValueError, low=0, high=layout.starts)
    inputs.integer(meta["iteration"], "meta.iteration", ValueError, low=0, high=layout.iterations)
    if not isinstance(meta["done"], bool):
        raise ValueError(f"meta.done: expected true or false, got {shown(meta['done'])}")
    histories, best = meta["history"], meta["best_value"]
    if not (isinstance(histories, list) and isinstance(best, list) and len(histories) == len(best) == layout.members):
        raise ValueError(f"meta: expected a history and a best value for each of {layout.members} member(s)")
    for m, value in enumerate(best):
        inputs.number(value, f"meta.best_value[{m}]", ValueError, finite=False)
    for m, message in inputs.check_keys(
        meta["failed"], "meta.failed", [str(m) for m in range(layout.members)], ValueError, what="member"
    ).items():
        if not isinstance(message, str):
            raise ValueError(f"meta.failed.{m}: expected a message, got {shown(message)}")
    for m, history in enumerate(histories):
        where = f"meta.history[{m}]"
        if not isinstance(history, list) or len(history) > layout.entries():
            raise ValueError(f"{where}: expected a list of at most {layout.entries()} entries")
        for k, h in enumerate(history):
            inputs.check_keys(
                h,
                f"{where}[{k}]",
                ("start", "iteration", "objective", "z"),
                ValueError,
                required=("start", "iteration", "objective", "z"),
            )
            inputs.integer(h["start"], f"{where}[{k}].start", ValueError, low=0, high=layout.starts - 1)
            inputs.integer(h["iteration"], f"{where}[{k}].iteration", ValueError, low=0, high=layout.iterations)
            inputs.number(h["objective"], f"{where}[{k}].objective", ValueError, finite=False)
            inputs.check_keys(h["z"], f"{where}[{k}].z", layout.z, ValueError, required=layout.z, what="field")


def load_checkpoint(path: Path, digest: str, layout: CheckpointLayout) -> TunerState | None:
    """The checkpoint at ``path`` if there is one (None otherwise), checked against ``layout`` (the run's settings).

    A regular file no larger than ``layout`` implies, read as plain arrays (``allow_pickle=False``: nothing in it
    runs).  Its ``meta`` is read first, and a checkpoint of another configuration (``digest``) refused; then every
    member's declared size, shape and dtype are checked from the zip's directory and the arrays' headers before any
    array is loaded (a zip bomb or a crafted header is refused, not decompressed), and its JSON; each group of arrays
    (``z``, ``best``, ``opt``) is whole or absent, ``best`` is there, and ``z`` and ``opt`` come together.  Anything
    else is refused with one line (:class:`ParameterError`), never a traceback.
    """
    if not os.path.lexists(path):
        return None
    fix = "delete it or use --fresh"
    try:
        data = inputs.read_bytes(path, "pusupu checkpoint", ParameterError, limit=layout.file_bytes())
    except ParameterError as e:
        raise ParameterError(f"{e}; {fix}") from None
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            infos = {info.filename: info for info in zf.infolist()}
            if len(infos) != len(zf.infolist()) or "meta.npy" not in infos:
                raise ValueError("expected one member of each name, meta.npy among them")
            shape, dtype = _array_header(zf, infos["meta.npy"], layout.meta_bytes())
            if dtype != np.uint8 or len(shape) != 1 or shape[0] > layout.meta_bytes():
                raise ValueError(f"meta: expected at most {layout.meta_bytes()} bytes, got {dtype} of shape {shape}")
            with np.load(io.BytesIO(data), allow_pickle=False) as f:
                meta = json.loads(bytes(f["meta"]).decode())
                if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
                    raise ValueError(f"not a {CHECKPOINT_FORMAT} file")
                if meta.get("digest") != digest:
                    raise ParameterError(
                        f"{path}: checkpoint of another configuration (hash "
                        f"{shown(meta.get('digest'))}, this one {digest}); use --fresh or another --out"
                    )
                expected = layout.arrays()
                for name, info in infos.items():
                    key = name.removesuffix(".npy")
                    if key == "meta":
                        continue
                    if not name.endswith(".npy") or key not in expected:
                        raise ValueError(f"unexpected member {shown(name)}")
                    want = expected[key]
                    got = _array_header(zf, info, int(np.prod(want[0])) * want[1].itemsize)
                    if got != want:
                        raise ValueError(
                            f"{key}: expected {want[1]} of shape {want[0]}, got {got[1]} of shape {got[0]}"
                        )
                _check_meta(meta, layout)
                groups = {g: sorted(k for k in expected if k.startswith(g + "/")) for g in ("z", "best", "opt")}
                held = {g: [k for k in names if k + ".npy" in infos] for g, names in groups.items()}
                for g, names in held.items():
                    if names and names != groups[g]:
                        raise ValueError(f"{next(k for k in groups[g] if k not in names)} missing")
                needed = {"z": held["opt"], "best": True, "opt": held["z"]}  # z and opt: both or neither
                missing = [g for g, need in needed.items() if need and not held[g]]
                if missing:
                    raise ValueError(f"missing arrays: {', '.join(missing)}")
                arrays = {k: np.asarray(f[k]) for k in f.files if k != "meta"}
    except ParameterError:
        raise
    except CHECKPOINT_ERRORS as e:
        raise ParameterError(f"{path}: not a pusupu checkpoint ({e}); {fix}") from None
    z = {k[2:]: v for k, v in arrays.items() if k.startswith("z/")} or None
    best = {k[5:]: v for k, v in arrays.items() if k.startswith("best/")} or None
    leaves = [arrays[f"opt/{k}"] for k in range(len(held["opt"]))]
    opt = jax.tree.unflatten(jax.tree.structure(layout.opt), leaves) if leaves else None
    return TunerState(
        digest=meta["digest"],
        z=z,
        opt=opt,
        history=[[Evaluation.from_json(h) for h in history] for history in meta["history"]],
        best_value=np.asarray(meta["best_value"], dtype=float),
        best_z={k: np.array(v) for k, v in (best or {}).items()},
        failed={int(m): message for m, message in meta["failed"].items()},
        start=meta["start"],
        iteration=meta["iteration"],
        done=meta["done"],
    )
