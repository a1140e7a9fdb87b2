"""The one exception type for user mistakes.

A `UserError` is something the user can fix (missing file, bad config value, unknown preset).
The command line prints its message as one line and exits non-zero; every other exception is a
bug and keeps its traceback.
"""


class UserError(Exception):
    """A mistake in the user's input. The message names the problem and the fix."""


def refuse_unused(options: list[tuple[str, bool, str]]) -> None:
    """One `UserError` for the first option given where it does nothing: each entry is (flag,
    whether it was given where it does not apply, what it is for), e.g. ("--frame",
    screenshot is None, "--screenshot FILE.png") -> `--frame is only for --screenshot FILE.png;
    drop it`."""
    for flag, unused, purpose in options:
        if unused:
            raise UserError(f"{flag} is only for {purpose}; drop it")
