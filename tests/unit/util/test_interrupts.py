"""Ctrl-C from the Python API after gmsh reset SIGINT (util/interrupts.python_interrupts)."""

import os
import signal

import pytest

from fenics_elasto.util.interrupts import python_interrupts


def test_ctrl_c_interrupts_where_gmsh_reset_it():
    """gmsh.initialize() leaves SIGINT at SIG_DFL, which would end the process; inside the
    block it raises KeyboardInterrupt (the estimate's best so far is kept), and the
    handler comes back after. A handler of the caller's is left alone."""
    import gmsh

    before = signal.getsignal(signal.SIGINT)
    try:
        gmsh.initialize()
        gmsh.finalize()
        assert signal.getsignal(signal.SIGINT) == signal.SIG_DFL  # what a user's script is left with
        with pytest.raises(KeyboardInterrupt), python_interrupts():
            os.kill(os.getpid(), signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) == signal.SIG_DFL
        seen = []
        signal.signal(signal.SIGINT, lambda *_: seen.append(1))
        with python_interrupts():
            os.kill(os.getpid(), signal.SIGINT)
        assert seen == [1]
    finally:
        signal.signal(signal.SIGINT, before)
