"""The one exception type that the command line reports without a traceback."""


class BcidError(Exception):
    """
    A user-facing error: bad input file, bad argument, missing topic, ...

    The ``bcid`` command prints its message on one line to stderr and exits
    non-zero (the traceback only with ``--debug``).
    """
