"""Imported by multiprocessing's fork server alone (first of :data:`omnirecon.capture.process.PRELOAD`): the server
asks for SIGKILL when the command that started it ends (Linux ``prctl(PR_SET_PDEATHSIG)``; elsewhere nothing), so
a killed command takes the server, and with it the SfM child, at once (the server's own exit ran the interpreter's
shutdown with torch and pycolmap loaded first: seconds in which the child went on writing)."""

import signal
import sys


def _in_fork_server() -> bool:
    """Whether this interpreter is multiprocessing's fork server (``python -c 'from multiprocessing.forkserver
    import main; ...'``)."""
    return sys.argv[:1] == ["-c"] and "multiprocessing.forkserver" in sys.modules


if _in_fork_server():
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
