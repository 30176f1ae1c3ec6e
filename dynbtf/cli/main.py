"""Entry point of the ``dynbtf`` command.

User mistakes (:class:`dynbtf.errors.DynBTFError`) are printed as one clear line
on standard error with exit status 2, never as a traceback; so are the operating system's
refusals met while reading or writing (:class:`OSError`: a full disk, a read-only file
system, a path under a file), e.g. ``dynbtf: error: out.png: no space left on device``.
"""

from __future__ import annotations

import os
import sys

from ..errors import DynBTFError
from .app import app

# Command modules register themselves on ``app`` when imported.
from . import data_commands  # noqa: F401,E402
from . import render_commands  # noqa: F401,E402
from . import model_commands  # noqa: F401,E402
from . import simulate_commands  # noqa: F401,E402
from . import compare_commands  # noqa: F401,E402
from . import synth_commands  # noqa: F401,E402
from . import fit_many_commands  # noqa: F401,E402
from . import export_commands  # noqa: F401,E402
from . import system_commands  # noqa: F401,E402
from . import compile_commands  # noqa: F401,E402

__all__ = ["app", "main"]


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    from .app import mark_command_start

    mark_command_start(include_process=argv is None)  # the installed `dynbtf` command: from the process's start
    try:
        status = app(args=argv, prog_name="dynbtf", standalone_mode=False)  # a command's typer.Exit code
        if isinstance(status, int) and status != 0:
            return status
    except DynBTFError as e:
        print(f"dynbtf: error: {e}", file=sys.stderr)
        if argv is None and getattr(e, "leave_without_finalizing", False):
            # a library loaded but unusable (an old LLVM under Dr.Jit) may hang in its shutdown at exit, at
            # random: the process leaves at once, its one line written
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(2)
        return 2
    except OSError as e:  # the environment refused a read or write (a full disk, a read-only file system)
        from ..io import os_error_message

        print(f"dynbtf: error: {os_error_message(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("dynbtf: interrupted (long jobs resume when run again with the same output)", file=sys.stderr)
        return 130
    except SystemExit as e:  # typer/click usage errors already printed
        return int(e.code or 0)
    except Exception as e:  # usage errors in non-standalone mode (typer's bundled click, or click)
        if type(e).__name__ == "Abort":
            return 130
        if callable(getattr(e, "show", None)) and isinstance(getattr(e, "exit_code", None), int):
            e.show()  # "Usage: ... Error: No such option: --bogus"
            return e.exit_code
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main())
