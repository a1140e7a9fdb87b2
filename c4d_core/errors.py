"""The one exception type for user mistakes.

A `UserError` is something the user can fix (missing file, bad config value, unknown preset).
The command line prints its message as one line and exits non-zero; every other exception is a
bug and keeps its traceback.
"""


class UserError(Exception):
    """A mistake in the user's input. The message names the problem and the fix."""
