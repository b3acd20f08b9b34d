"""The exit codes of every ``dmpc`` command and process (documented in the README)."""

EXIT_OK = 0
"""Finished, and the run's verdict is ok."""
EXIT_FAILED = 1
"""A process failed (crashed, lost its peers, could not start)."""
EXIT_INPUT = 2
"""A usage or input error: bad flag, invalid scenario, a design that cannot be used."""
EXIT_VERDICT = 3
"""The run completed, but its verdict is ``failed`` (constraints broken, infeasible, diverged...)."""
EXIT_ADDRESS_IN_USE = 4
"""A process could not listen: another socket holds the address of its ``--listen`` endpoint.
``dmpc run`` reads it from its plant to start the run again on another port."""
EXIT_INTERRUPTED = 130
"""Stopped by Ctrl-C or SIGTERM."""
