"""What the ``pusupu`` commands share: checked inputs, the machine of ``--machine``, a plot's output path."""

from __future__ import annotations

import contextlib
import os

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


def check_plot_path(path):
    """``--plot PATH``: a PNG file to write in an existing, writable folder (a regular file or nothing there now)."""
    from pusupu_jax.files import check_output

    folder = os.path.dirname(os.path.abspath(path))
    if not path or os.path.isdir(path):
        raise ParameterError(f"--plot: expected the path of a PNG file, got the folder {path!r}")
    if not os.path.isdir(folder):
        raise ParameterError(f"--plot: expected a PNG path in an existing folder, got {path!r}")
    if not os.access(folder, os.W_OK):
        raise ParameterError(f"--plot: cannot write in the folder {folder!r}")
    try:
        check_output(path)
    except ParameterError as e:
        raise ParameterError(f"--plot: {e}") from None


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
