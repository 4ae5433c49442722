"""The one exception type that the command line turns into a one-line error."""


class HeadforgeError(Exception):
    """A user-facing problem (bad input, missing file, wrong shape). The CLI prints its
    message on one line and exits non-zero, without a traceback."""
