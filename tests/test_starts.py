"""The windows' start states kept on disk (pusupu_jax.tune.starts): read back as written, and a file that is damaged,
crafted or missing is ignored (the states are then computed again).  A problem that reads them back is checked in
tests/test_batch.py, against a forward pass."""

import hashlib
import io
import warnings

import jax
import numpy as np

from pusupu_jax.tune import starts

TREE = {"qpos": np.linspace(0.0, 1.0, 6).reshape(3, 2), "step": np.arange(4, dtype=np.int32)}


def structure():
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), TREE)


def _write(path, blob):
    path.write_bytes(hashlib.sha256(blob).digest() + blob)


def test_kept_start_states_read_back_bit_for_bit(tmp_path):
    path = tmp_path / "starts" / "a.npz"
    starts.keep(path, TREE)
    got = starts.load(path, structure)
    assert jax.tree.structure(got) == jax.tree.structure(TREE)
    assert all(np.array_equal(got[k], TREE[k]) and got[k].dtype == TREE[k].dtype for k in TREE)


def test_a_damaged_crafted_or_missing_file_is_ignored(tmp_path):
    path = tmp_path / "a.npz"
    assert starts.load(path, structure) is None  # none there
    path.write_bytes(b"x" * 40)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert starts.load(path, structure) is None  # fails its checksum
    assert "fails its checksum" in str(caught[0].message)
    _write(path, b"PK\x03\x04" + b"not a zip" * 8)
    assert starts.load(path, structure) is None
    buffer = io.BytesIO()
    np.savez(buffer, leaf0=np.array([object()], dtype=object), leaf1=np.arange(4, dtype=np.int32))
    _write(path, buffer.getvalue())
    assert starts.load(path, structure) is None  # objects: never unpickled
    buffer = io.BytesIO()
    np.savez(buffer, leaf0=np.zeros((3, 2), np.float32), leaf1=np.arange(4, dtype=np.int32))
    _write(path, buffer.getvalue())
    assert starts.load(path, structure) is None  # another dtype than the states'
    buffer = io.BytesIO()
    np.savez(buffer, leaf0=np.zeros((3, 2)))
    _write(path, buffer.getvalue())
    assert starts.load(path, structure) is None  # a leaf missing
