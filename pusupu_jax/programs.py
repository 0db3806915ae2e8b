"""Traced programs kept on disk beside JAX's compilation cache, so that a new process need not trace them again.

JAX's persistent compilation cache (:func:`pusupu_jax.runtime.setup_jax`) keeps what XLA compiled, but every
process first traces and lowers its functions in Python to find it there.  For the tuner's gradient through the
MJX rollout that is about 25 s on a 2-core CPU, paid again by every ``pusupu tune``, resumed run and notebook
kernel.  A :class:`Program` exports its function's lowered program (:mod:`jax.export`: StableHLO in a flatbuffer,
read without unpickling anything) at its first call for each argument signature, keeps it under ``programs/`` in
the compilation cache's folder, and in a later process loads that file instead of tracing.  Both processes run
the exported program (``jax.jit(exported.call)``), so they compile the same module, and the second one finds its
executable in the compilation cache; results are bitwise those of the function jitted directly.

A file is named by a hash of everything its program depends on: the caller's ``key`` (all that the function reads
besides its arguments), the source of this package and of the ``sources`` folders named, the versions of jax,
jaxlib, mujoco, mujoco-mjx and numpy, the platform, the JAX settings that change a trace (float64, matmul precision,
dtype promotion), and the arguments' structure, shapes and dtypes.  It starts with the SHA-256 of the rest, checked
on reading; then the names of the pytree node types its outputs hold beyond tuples, lists and dicts (JSON: a run's
carry holds the cascade's states and MJX's data), each of a module in :data:`TRUSTED_MODULES`, imported and its
serialization registered before the program is read; then the program.  The files trust the same folder as the
compilation cache's executables, which are machine code.  A file that fails its checksum, does not deserialise, was
made for other arguments or does not lower is traced again and replaced, with a warning; a function that cannot be
exported is only jitted, with a warning; with no compilation cache configured nothing is kept and the function is
only jitted.  The folder can be deleted.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import importlib
import importlib.metadata
import json
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import export

from .files import write_atomic

if TYPE_CHECKING:
    from jax.sharding import Mesh
    from jax.stages import Lowered, Wrapped
    from jax.tree_util import PyTreeDef

SUFFIX = ".jaxexport"
HERE = Path(__file__).parent
_VERSIONED = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy")
_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion")


# The modules whose pytree node types (a run's carry: the cascade's states, MJX's data) a kept program's outputs may
# hold: a file names them, and a process that loads it imports them and registers their serialization with jax.export
# (nothing else is imported or built from a file).
TRUSTED_MODULES = ("pusupu_jax.", "mujoco.mjx.")
_registered: set[type] = set()  # the node types whose serialization this module registered


class UnstableKey(ValueError):
    """A value whose description would differ between processes (an object known only by its address)."""


def _name(t: type) -> str:
    return f"{t.__module__}.{t.__qualname__}"


def describe(x: Any) -> str:
    """A description of ``x`` that is the same in every process for equal values: containers, scalars, strings,
    arrays (dtype, shape and a hash of the bytes), enums, dataclasses and NamedTuples by their class and fields,
    pytree definitions node by node (their static data included), and objects that wrap one array as ``.array``
    (MJX's static arrays).  Anything else (an array of objects included) raises :class:`UnstableKey`."""
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes, np.generic)):
        return repr(x)
    if isinstance(x, enum.Enum):
        return f"{_name(type(x))}.{x.name}"
    if isinstance(x, jax.Array):
        x = np.asarray(x)
    if isinstance(x, np.ndarray):
        if x.dtype.hasobject:
            raise UnstableKey("no stable description of an array of Python objects")
        return f"array({x.dtype},{x.shape},{hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()[:24]})"
    if isinstance(x, jax.tree_util.PyTreeDef):
        return _describe_treedef(x)
    if isinstance(x, type):
        return _name(x)
    if isinstance(x, tuple) and hasattr(x, "_fields"):
        return f"{_name(type(x))}({','.join(f'{f}={describe(v)}' for f, v in zip(x._fields, x))})"
    if isinstance(x, (list, tuple, dict)):
        items = sorted(x.items(), key=lambda kv: repr(kv[0])) if isinstance(x, dict) else enumerate(x)
        return f"{_name(type(x))}[{','.join(f'{describe(k)}:{describe(v)}' for k, v in items)}]"
    if dataclasses.is_dataclass(x):
        fields = ",".join(f"{f.name}={describe(getattr(x, f.name))}" for f in dataclasses.fields(x))
        return f"{_name(type(x))}({fields})"
    if isinstance(getattr(x, "array", None), np.ndarray):  # MJX's static arrays, wrapped to hash by content
        return f"{_name(type(x))}({describe(x.array)})"
    raise UnstableKey(f"no stable description of a {_name(type(x))}")


def _describe_treedef(treedef: PyTreeDef) -> str:
    node = treedef.node_data()
    head = "*" if node is None else f"{describe(node[0])}{describe(node[1])}"
    return head + "(" + ",".join(_describe_treedef(c) for c in treedef.children()) + ")"


def _node_types(treedef: PyTreeDef) -> set[type]:
    """The node types of ``treedef`` that jax.export does not serialize itself (every one but tuples, lists, dicts
    and None)."""
    node = treedef.node_data()
    found = set() if node is None or node[0] in (tuple, list, dict, type(None)) else {node[0]}
    for child in treedef.children():
        found |= _node_types(child)
    return found


def _register(t: type) -> None:
    """Register the serialization of node type ``t`` with jax.export (once): a NamedTuple by its fields; another node
    by its static data, which must be numbers, strings, None, tuples and lists of them, or MJX's wrapped NumPy arrays
    (:func:`_encode`).  ``TypeError`` for a type outside :data:`TRUSTED_MODULES`."""
    if t in _registered:
        return
    name = _type_name(t)
    if not t.__module__.startswith(TRUSTED_MODULES):
        raise TypeError(f"an output of type {name}, outside {TRUSTED_MODULES}")
    if issubclass(t, tuple) and hasattr(t, "_fields"):
        export.register_namedtuple_serialization(t, serialized_name=name)
    else:
        export.register_pytree_node_serialization(
            t,
            serialized_name=name,
            serialize_auxdata=lambda aux: json.dumps(_encode(aux)).encode(),
            deserialize_auxdata=lambda data: _decode(json.loads(data)),
        )
    _registered.add(t)


def _encode(x: Any) -> Any:
    """A node's static data as JSON (:func:`_register`); ``TypeError`` for anything else."""
    # NumPy scalars first (np.float64 is a float): read back as the same NumPy type, since a node's static data is in
    # its structure, which names the programs it enters
    if isinstance(x, (np.integer, np.floating, np.bool_)):
        return {"numpy": x.dtype.str, "value": x.item()}
    if x is None or isinstance(x, (bool, int, float, str)):
        return x
    if isinstance(x, (tuple, list)):
        return {type(x).__name__: [_encode(v) for v in x]}
    wrapped = getattr(x, "array", None)
    if (
        isinstance(wrapped, np.ndarray)
        and type(x).__module__.startswith(TRUSTED_MODULES)
        and not wrapped.dtype.hasobject
    ):
        return {
            "wrapped": _type_name(type(x)),
            "dtype": wrapped.dtype.str,
            "shape": wrapped.shape,
            "values": wrapped.ravel().tolist(),
        }
    raise TypeError(f"static data of type {_name(type(x))}")


def _decode(x: Any) -> Any:
    """The inverse of :func:`_encode`."""
    if isinstance(x, dict) and "numpy" in x:
        return np.dtype(x["numpy"]).type(x["value"])
    if isinstance(x, dict) and "wrapped" in x:
        array = np.asarray(x["values"], dtype=np.dtype(x["dtype"])).reshape(x["shape"])
        return _trusted_type(x["wrapped"])(array)
    if isinstance(x, dict):
        ((kind, items),) = x.items()
        return {"tuple": tuple, "list": list}[kind](_decode(v) for v in items)
    return x


def _type_name(t: type) -> str:
    """``module:qualname``, as a kept file names a type (:func:`_trusted_type` reads it)."""
    return f"{t.__module__}:{t.__qualname__}"


def _trusted_type(name: str) -> Any:
    """The class ``module:qualname`` of a module in :data:`TRUSTED_MODULES` (imported); ``TypeError`` for another."""
    module, _, qualname = name.partition(":")
    if not module.startswith(TRUSTED_MODULES):
        raise TypeError(f"a type outside {TRUSTED_MODULES}: {name}")
    found: Any = importlib.import_module(module)
    for part in qualname.split("."):
        found = getattr(found, part)
    if not isinstance(found, type):
        raise TypeError(f"not a type: {name}")
    return found


def _source_digest(folder: Path) -> str:
    """Every ``.py`` file under ``folder``, names and bytes (read again each time: a notebook may have edited one)."""
    h = hashlib.sha256()
    for path in sorted(folder.rglob("*.py")):
        h.update(str(path.relative_to(folder)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def _versions() -> str:
    out = []
    for name in _VERSIONED:
        try:
            out.append(f"{name}={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            out.append(f"{name}=-")
    return ",".join(out)


def platform() -> str:
    """The platform this thread computes on: its default device's (``jax.default_device``, which
    :func:`pusupu_jax.devices.select` sets, or a ``with`` block), else JAX's default backend's."""
    device = jax.config.jax_default_device  # type: ignore[attr-defined]  # JAX defines its flags at run time
    if device is None:
        return jax.default_backend()
    return device if isinstance(device, str) else device.platform


def fingerprint(parts: Sequence[str], sources: tuple[Path, ...] = ()) -> str:
    """A hash of ``parts`` and of everything else a traced computation depends on: the versions of jax, jaxlib,
    mujoco, mujoco-mjx and numpy, the platform (:func:`platform`), the JAX settings that change a trace, and the
    source of this package and of the ``sources`` folders."""
    h = hashlib.sha256()
    settings = ",".join(f"{name}={getattr(jax.config, name)}" for name in _SETTINGS)
    extra = (_versions(), platform(), settings, *(_source_digest(f) for f in (HERE, *sources)))
    for part in (*parts, *extra):
        h.update(part.encode() + b"\0")
    return h.hexdigest()


def _signature(leaves: list[Any], tree: PyTreeDef) -> tuple[PyTreeDef, tuple[str, ...]]:
    """What a :class:`Program` keeps one program for: the arguments' structure and their types."""
    return tree, tuple(str(jax.typeof(x)) for x in leaves)


def cache_folder() -> Path | None:
    """``programs/`` in JAX's compilation cache folder (set by :func:`pusupu_jax.runtime.setup_jax`), or None."""
    folder = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]  # JAX defines its flags at run time
    return None if not folder else Path(folder) / "programs"


class Program:
    """``fun`` jitted through an exported program kept on disk (module docstring); call it as ``fun``.

    ``key``: a stable description (:func:`describe`) of all that ``fun`` reads besides its arguments, or a function
    that returns one (called when a signature is first traced or loaded, so that the name is taken from the state
    the trace reads, should that have changed since).  ``sources``: folders of Python code that ``fun``'s program is
    traced from, besides this package.  ``folder``: where the programs are kept (default :func:`cache_folder`).
    ``loaded`` counts the signatures read from disk.  With ``to_host`` (the default) the outputs come back as host
    copies (uncommitted arrays, as a plain jit returns them): for programs with small outputs, such as a value and its
    gradient, that other programs take as arguments.  Without, they stay where the program put them (committed to its
    device): for a program whose outputs only it takes back (a run's carry from one chunk to the next) or that are
    fetched to the host anyway.

    ``mesh``: the devices a program that lays its work over several (:func:`pusupu_jax.devices.spread_rows`) runs
    on; its arguments and outputs are whole on each of them (replicated), and its file is for that many devices.
    """

    def __init__(
        self,
        fun: Callable[..., Any],
        key: str | Callable[[], str],
        sources: tuple[Path, ...] = (),
        folder: Path | None = None,
        mesh: Mesh | None = None,
        to_host: bool = True,
    ) -> None:
        self.fun, self.key, self.folder, self.mesh, self.to_host = fun, key, folder, mesh, to_host
        self.sources = tuple(Path(s) for s in sources)
        self.loaded = 0
        self._calls: dict[tuple[PyTreeDef, tuple[str, ...]], Wrapped] = {}
        self._ahead: dict[tuple[PyTreeDef, tuple[str, ...]], threading.Thread] = {}  # compile_ahead's, not joined

    def __call__(self, *args: Any) -> Any:
        leaves, tree = jax.tree.flatten(args)
        call = self._call(leaves, tree)
        if not self.to_host:
            return call(*leaves)
        # an exported call's outputs are committed to their device, a plain jit's (of uncommitted arguments) are not;
        # fed back (the optimiser's next step, the next start states) they would change the arguments' placement, and
        # every program they reach, this one included, would be lowered and compiled again for it: small outputs
        # (a value and its gradient) come back as plain jit's would
        return jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), call(*leaves))

    def compile_ahead(self, *args: Any) -> None:
        """Load (or trace and keep) and compile the program for arguments of ``args``' types in a thread of its own,
        while the caller goes on with other work (a tuner's forward pass over its paths): the first call with
        arguments of those types waits for that thread, then runs what it compiled.  XLA's compile and the
        compilation cache's load run outside Python's lock, so on a machine of two cores or more they overlap the
        caller's own.  What fails there is left to that first call, which does it again and raises."""
        leaves, tree = jax.tree.flatten(args)
        signature = _signature(leaves, tree)
        if signature in self._calls or signature in self._ahead:
            return

        def compile() -> None:
            try:
                self._lookup(leaves, tree, signature).lower(*leaves).compile()
            except Exception:  # noqa: BLE001  the first call does it again, and raises
                pass

        thread = self._ahead[signature] = threading.Thread(target=compile, name="compile_ahead", daemon=True)
        thread.start()

    def eval_shape(self, *args: Any) -> Any:
        """The outputs' structure for ``args`` (``jax.ShapeDtypeStruct`` leaves), from the program on disk when there
        is one (nothing traced), else traced and kept as a call would."""
        leaves, tree = jax.tree.flatten(args)
        return jax.eval_shape(self._call(leaves, tree), *leaves)

    def cache_size(self) -> int:
        """The executables this program holds in this process: one per argument signature (as a jitted function's
        ``_cache_size``)."""
        return sum(call._cache_size() for call in self._calls.values())  # type: ignore[attr-defined]  # jax's own

    def lower(self, *args: Any) -> Lowered:
        """The lowered program for ``args`` (traced and exported, or loaded), to time or inspect; its ``compile()``
        takes the arguments' leaves (``jax.tree.leaves(args)``) and returns the outputs as placed by the device."""
        leaves, tree = jax.tree.flatten(args)
        return self._call(leaves, tree).lower(*leaves)

    def _call(self, leaves: list[Any], tree: PyTreeDef) -> Wrapped:
        signature = _signature(leaves, tree)
        ahead = self._ahead.pop(signature, None)
        if ahead is not None:  # compile_ahead's thread: its program, compiled (or what it left to this call)
            ahead.join()
        return self._lookup(leaves, tree, signature)

    def _lookup(self, leaves: list[Any], tree: PyTreeDef, signature: tuple[PyTreeDef, tuple[str, ...]]) -> Wrapped:
        call = self._calls.get(signature)
        if call is None:
            call = self._calls[signature] = self._program(leaves, tree, signature[1])
        return call

    def digest(self, tree: PyTreeDef, avals: Sequence[str]) -> str:
        """The file name's hash for arguments of structure ``tree`` and types ``avals``."""
        key = self.key() if callable(self.key) else self.key
        devices = f"devices={1 if self.mesh is None else self.mesh.size}"
        return fingerprint((key, devices, describe(tree), ";".join(avals)), self.sources)

    def _program(self, leaves: list[Any], tree: PyTreeDef, avals: Sequence[str]) -> Wrapped:
        def flat(*xs: Any) -> Any:
            return self.fun(*jax.tree.unflatten(tree, xs))

        jit = self._jit
        folder = self.folder or cache_folder()
        if folder is None:
            return jit(flat)
        try:
            path = folder / (self.digest(tree, avals) + SUFFIX)
        except UnstableKey as e:
            warnings.warn(f"pusupu_jax.programs: not kept on disk ({e})", stacklevel=4)
            return jit(flat)
        if path.exists():
            try:
                call = self._load(path, leaves, jit)
                self.loaded += 1
                return call
            except Exception as e:  # damaged, foreign, or for other arguments: trace again and replace it
                warnings.warn(
                    f"pusupu_jax.programs: {path} did not load ({type(e).__name__}: {e}); tracing again", stacklevel=4
                )
        try:
            # for the platform this thread computes on (a GPU job's forward passes may run on the host's CPU)
            exported = export.export(jit(flat), platforms=("cpu",) if platform() == "cpu" else None)(*leaves)
        except Exception as e:  # what jax.export refuses (host callbacks, some custom calls): jit it as it is
            warnings.warn(
                f"pusupu_jax.programs: not exported, traced in this process only ({type(e).__name__}: {e})",
                stacklevel=4,
            )
            return jit(flat)
        try:
            types = _node_types(exported.out_tree)
            for t in types:
                _register(t)
            header = json.dumps(sorted(map(_type_name, types))).encode()
            body = len(header).to_bytes(4, "little") + header + bytes(exported.serialize())
            folder.mkdir(parents=True, exist_ok=True)
            write_atomic(path, hashlib.sha256(body).digest() + body)
        except Exception as e:  # a full or read-only disk, an output jax.export cannot write, no flatbuffers
            warnings.warn(f"pusupu_jax.programs: could not keep {path} ({type(e).__name__}: {e})", stacklevel=4)
        return jit(exported.call)

    def _jit(self, fun: Callable[..., Any]) -> Wrapped:
        """``jax.jit(fun)``; over :attr:`mesh`, with every argument and output whole on each of its devices."""
        if self.mesh is None:
            return jax.jit(fun)
        from jax.sharding import NamedSharding, PartitionSpec

        whole = NamedSharding(self.mesh, PartitionSpec())  # type: ignore[no-untyped-call]  # jax leaves P() unannotated
        return jax.jit(fun, in_shardings=whole, out_shardings=whole)

    @staticmethod
    def _load(path: Path, leaves: list[Any], jit: Callable[[Callable[..., Any]], Wrapped]) -> Wrapped:
        """The jitted call of the program in ``path``, checked: its checksum, its arguments' types, and a lowering."""
        data = path.read_bytes()
        body = data[32:]
        if hashlib.sha256(body).digest() != data[:32]:
            raise ValueError("checksum mismatch")
        size = int.from_bytes(body[:4], "little")
        for name in json.loads(body[4 : 4 + size]):  # the outputs' node types, registered before they are read
            _register(_trusted_type(name))
        exported = export.deserialize(bytearray(body[4 + size :]))
        want = [jax.typeof(x) for x in leaves]
        if [(a.shape, a.dtype) for a in exported.in_avals] != [(a.shape, a.dtype) for a in want]:
            raise ValueError("made for other argument types")
        call = jit(exported.call)
        call.lower(*leaves)  # parses the module (cached: the first call does not lower again)
        return call
