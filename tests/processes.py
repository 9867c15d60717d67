"""Subprocess helpers for the tests that press Ctrl-C on a command."""

import signal


def interruptible() -> None:
    """preexec_fn for subprocess.Popen: the child takes SIGINT (Ctrl-C) as one started from a
    terminal does. A shell without job control starts background jobs (`bash .ci/run &`) with
    SIGINT ignored, every child inherits that, and Python then never raises KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
