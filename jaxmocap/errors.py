"""The one base class of user-input errors.

Every file-format or argument error the library raises for bad *user input* derives from
:class:`InputError` (a ``ValueError``): its message is one line naming the file, the field and
what was expected. The command line prints it and exits with code 2; anything else is a bug and
keeps its traceback.
"""


class InputError(ValueError):
    """Bad user input (a file, a field, an argument): a one-line, actionable message."""


class UsageError(InputError):
    """Bad command-line usage: reported as one line on stderr with exit code 2."""
