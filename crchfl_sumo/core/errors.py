"""The one error type for mistakes a user can make (bad file, bad key, impossible budget).

The CLI prints its message without a traceback and exits with status 2, so the
message must name the file or key at fault and say how to fix it.
"""


class CrchflError(Exception):
    """A user-caused error: the message names what is wrong and the fix."""
