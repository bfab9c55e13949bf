"""Errors a user can act on: the CLI prints them as one line, without a traceback."""


class UserError(Exception):
    """Bad input (missing file, wrong layout, unknown config key...): the message says what to do."""


class DataError(UserError):
    """A data file is missing, unreadable or malformed; the message names the file and the reason."""
