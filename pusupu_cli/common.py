"""What the ``pusupu`` commands share: checked inputs, the machine of ``--machine``, a plot's output path."""

from __future__ import annotations

import contextlib
import os
import sys

from pusupu_jax.inputs import one_line
from pusupu_jax.params import ParameterError


@contextlib.contextmanager
def checking(source: str):
    """The inputs named ``source`` are read and checked inside: a ValueError, OverflowError or FloatingPointError
    raised there (by numpy, python-control or float arithmetic on an absurd value) is the input's fault and becomes a
    ParameterError naming ``source`` (one line, exit 2).  Raised later, in the work, such an error is a bug and keeps
    its traceback, as every other exception does."""
    try:
        yield
    except ParameterError:
        raise
    except (ValueError, OverflowError, FloatingPointError) as e:
        raise ParameterError(f"{source}: cannot use these values ({type(e).__name__}: {e})") from None


def loads_along(machine, specs: list[str], servo, rates) -> dict:
    """:func:`pusupu_jax.machine_file.margin_loads` of ``machine`` along the paths ``specs`` (``--trajectory``), each
    sampled at ``rates`` and checked against the machine with ``servo``'s drives first."""
    from pusupu_jax import machine_file
    from pusupu_jax.paths import platform_path_from

    runs = []
    for spec in specs:
        with checking(f"--trajectory {spec}"):
            poses = platform_path_from(spec, machine.geometry.home, rates)
            check_path_on(machine, poses, servo, f"--trajectory {spec}", rates.dt_position)
        runs.append(machine_file.PathRun(poses))
    return machine_file.margin_loads(machine, runs)


def check_along_paths(g, machine, specs: list[str], floors, source: str) -> dict:
    """The gain check of ``g`` (a :class:`~pusupu_jax.gains.GainFile` read from ``source``) with the load at the
    lightest and the heaviest pose along the paths ``specs`` too (:func:`loads_along`); raises
    :class:`ParameterError` in one line.  Returns the loads."""
    from pusupu_jax import stability

    loads = loads_along(machine, specs, g.servo, g.rates)
    try:
        stability.check_loads(g.servo, g.hybrid, g.rates, g.mode, floors, loads, along=" and ".join(specs))
    except ParameterError as e:
        raise ParameterError(f"{source}: {e}") from None
    return loads


def check_output_path(path, option: str = "--plot", kind: str = "PNG"):
    """``OPTION PATH``: a file of ``kind`` to write in an existing, writable folder (a regular file or nothing there
    now), checked before any work."""
    from pusupu_jax.files import check_output, check_writable

    if not path:
        raise ParameterError(f"{option}: expected the path of a {kind} file, got an empty name")
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise ParameterError(f"{option}: expected the path of a {kind} file, got the folder {path!r}")
    if not os.path.isdir(folder):
        raise ParameterError(f"{option}: expected a {kind} path in an existing folder, got {path!r}")
    check_writable(folder, option)
    try:
        check_output(path)
    except ParameterError as e:
        raise ParameterError(f"{option}: {e}") from None


def check_plot_path(path):
    """``--plot PATH``: :func:`check_output_path` for a figure, PNG, SVG or PDF after its name's suffix (the rule
    that writes it, :func:`pusupu_jax.plots.plot_format`)."""
    from pusupu_jax.plots import plot_format

    check_output_path(path, "--plot", "PNG, SVG or PDF")
    try:
        plot_format(path)
    except ParameterError as e:
        raise ParameterError(f"--plot: {e}") from None


def check_log_path(path):
    """``--log PATH``: :func:`check_output_path` for an MCAP log, its name ending ``.mcap``."""
    from pathlib import Path

    check_output_path(path, "--log", "MCAP")
    if Path(path).suffix.lower() != ".mcap":
        raise ParameterError(f"--log: expected a name ending .mcap, got {path!r}")


def machine_of(args):
    """The machine of ``--machine FILE`` (checked; read once per command), or the built-in one."""
    from pusupu_jax import machine_file

    if getattr(args, "machine_loaded", None) is None:
        if getattr(args, "machine", None):
            with checking(f"--machine {args.machine}"):
                args.machine_loaded = machine_file.load(args.machine)
        else:
            args.machine_loaded = machine_file.Machine.default()
    return args.machine_loaded


def check_path_on(machine, poses, servo, where: str, dt_position: float | None = None, options=None) -> None:
    """:func:`pusupu_jax.paths.check_path` of ``poses`` on ``machine`` (its geometry, and its payload unless
    ``options`` are given) at ``dt_position`` [s] (default the default position period); ``where`` names the path in
    the error."""
    from pusupu_jax.params import LoopRates
    from pusupu_jax.paths import check_path

    check_path(
        poses,
        servo,
        LoopRates().dt_position if dt_position is None else dt_position,
        geom=machine.geometry,
        options=machine.options() if options is None else options,
        where=where,
    )


def say(message: str) -> None:
    """Print ``message`` on stderr as one line (:func:`pusupu_jax.inputs.one_line`: escaped, cut): every error line
    of the command goes through here, so that no input is echoed raw or whole."""
    print(one_line(message), file=sys.stderr)


def num(x, none="inf"):
    """A table cell: 4 significant digits; ``none`` where the value is None (infinite margin, unsettled step)."""
    return none if x is None else f"{x:.4g}"


def load_gains(args, check: bool = True):
    """The params file (or defaults) with a gain file's gains and rates in place, on the machine of ``--machine``,
    checked by :func:`pusupu_jax.stability.check` for ``args.mode`` (``check=False``: bounds only, for a diagnosis).
    With ``--machine``, the params file may set controller fields only: the drives are the machine's."""
    from pathlib import Path

    from pusupu_jax import machine_file, stability
    from pusupu_jax.files import read_yaml_mapping
    from pusupu_jax.params_file import SECTIONS, load_params_file
    from pusupu_jax.runtime import setup_jax

    setup_jax()  # the checks' compiled programs come from the persistent cache after the first run
    machine = machine_of(args)
    with checking(f"--params {args.params}" if args.params else "the default parameters"):
        loaded = load_params_file(args.params)
        sections = read_yaml_mapping(Path(args.params), "section", SECTIONS) if args.params else {}
        # the linear model's load: a params file's load section, else the machine's (machine_file.axis_load)
        args.linear_load = loaded.load if sections.get("load") else machine_file.axis_load(machine)
        args.load_from_params = bool(sections.get("load"))
        if args.machine:
            servo = sections.get("servo") or {}
            clash = [name for name in servo if name in machine.drives]
            if clash:
                raise ParameterError(
                    f"--params {args.params}: servo.{clash[0]}: expected controller fields only with "
                    f"--machine (the drives are the machine file's), got the drive field {clash[0]}"
                )
    if getattr(args, "gains", None):
        from pusupu_jax import gains

        with checking(f"--gains {args.gains}"):
            g = gains.load(args.gains, args.floors, check_stability=False, machine=machine)
        loaded = loaded._replace(servo=g.servo, hybrid=g.hybrid, rates=g.rates)
    elif args.machine and not args.params and not machine_file.is_builtin(machine):
        from pusupu_jax.start_gains import derive

        print(
            f"pusupu: no --gains: the start gains derived for machine {machine.name!r} (docs/machine.md; T0 "
            "identified on the MJX machine, about 30 s)",
            file=sys.stderr,
            flush=True,
        )
        with checking(f"--machine {args.machine}"):
            loaded = loaded._replace(servo=derive(machine, loaded.rates)[0])
    with checking(f"--machine {args.machine}" if args.machine else "the built-in machine"):
        loaded = loaded._replace(servo=machine.servo(loaded.servo))
    if args.imc_form:
        loaded = loaded._replace(servo=loaded.servo.replace(imc_form=args.imc_form))
    if check:
        try:
            stability.check(loaded.servo, loaded.hybrid, loaded.rates, args.mode, args.floors, load=args.linear_load)
        except ParameterError as e:
            raise ParameterError(f"{args.gains or args.params or 'the defaults'}: {e}") from None
    else:
        stability.check_values(loaded.servo, loaded.hybrid, loaded.rates)
    return loaded
