"""The training windows' start states kept on disk beside the compiled programs, so that a later run of the same job
does not run the forward pass over the whole paths again for gains it has already run it for.

A :class:`pusupu_jax.tune.run.Problem` renews its windows' start states with a forward pass over every scenario's
whole path (:meth:`~pusupu_jax.tune.run.Problem.refresh`): on the 2-core CPU about 10 s for the default job's two
paths, at its start and every ``refresh_every`` iterations.  Those states depend only on what the file's name
hashes (:func:`pusupu_jax.programs.fingerprint`): the problem's structure (its configuration, plant options, rates;
:func:`~pusupu_jax.tune.run.structure_key`), its start gains, the gains ``z``, every scenario's model arrays and
reference, the number of devices, and the source and versions of what computes them.  So a second run of a job
(or a notebook's second problem) loads the states its first run kept: bit for bit the arrays that run computed.
Beside the states at the start gains, the objective's terms there (its normalisers,
:meth:`~pusupu_jax.tune.run.WindowStarts.start_baseline`) are kept the same way: a second run then starts with one
gradient, not two.  So are the scenarios' references (:func:`pusupu_jax.tune.run.kept_reference`): a second run
neither checks its paths nor runs their inverse kinematics and dynamics again.

A file holds the states' arrays (``numpy.savez``, read with ``allow_pickle=False``) after the SHA-256 of the rest;
the states' structure comes from the problem (:meth:`~pusupu_jax.tune.run.Problem.starts_structure`), and a file
whose checksum, arrays or types do not match it is ignored (the states are computed again and the file replaced).
The files trust the same folder as the compilation cache's executables.  ``starts/`` can be deleted.
"""

from __future__ import annotations

import hashlib
import io
import warnings
import zipfile
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from pusupu_jax.files import write_atomic
from pusupu_jax.programs import cache_folder

FOLDER = "starts"
MAX_BYTES = 1 << 30  # a file larger than this is not read


def path_for(digest: str) -> Path | None:
    """The file of the start states named ``digest`` (in ``starts/`` beside ``programs/``), or None when no
    compilation cache is configured."""
    programs = cache_folder()
    return None if programs is None else programs.parent / FOLDER / f"{digest}.npz"


def load(path: Path, structure: Callable[[], Any]) -> Any | None:
    """The start states kept in ``path`` as a pytree of ``structure()`` (a tree of ``jax.ShapeDtypeStruct``: one leaf
    each, of that dtype and number of dimensions; asked for only when the file exists), or None if there is no such
    file or it does not match."""
    try:
        if not path.is_file() or path.stat().st_size > MAX_BYTES:
            return None
        data = path.read_bytes()
    except OSError:
        return None
    blob = data[32:]
    if hashlib.sha256(blob).digest() != data[:32]:
        warnings.warn(f"pusupu_jax.tune.starts: {path} fails its checksum; computing the start states again")
        return None
    leaves, tree = jax.tree.flatten(structure())
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as arrays:
            if sorted(arrays.files) != sorted(f"leaf{k}" for k in range(len(leaves))):
                return None
            kept = [arrays[f"leaf{k}"] for k in range(len(leaves))]
    except (ValueError, OSError, zipfile.BadZipFile):  # not an npz, a damaged one, or one holding objects
        return None
    if any(a.dtype != t.dtype or a.ndim != len(t.shape) for a, t in zip(kept, leaves)):
        return None
    return jax.tree.unflatten(tree, kept)


def kept(path: Path | None, structure: Callable[[], Any], compute: Callable[[], Any]) -> tuple[Any, bool]:
    """The arrays kept in ``path`` (read by :func:`load` with ``structure``, as JAX arrays), or else ``compute()``,
    then kept there; and whether they were read.  ``path`` None: computed, nothing kept."""
    stored = None if path is None else load(path, structure)
    if stored is not None:
        return jax.tree.map(jnp.asarray, stored), True
    value = compute()
    if path is not None:
        keep(path, value)
    return value, False


def keep(path: Path, starts: Any) -> None:
    """Write ``starts`` (a pytree of arrays) to ``path`` atomically; a full or read-only disk only warns."""
    buffer = io.BytesIO()
    np.savez(buffer, **{f"leaf{k}": np.asarray(x) for k, x in enumerate(jax.tree.leaves(starts))})
    blob = buffer.getvalue()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, hashlib.sha256(blob).digest() + blob)
    except OSError as e:
        warnings.warn(f"pusupu_jax.tune.starts: could not keep {path} ({e.strerror})")
