"""The one exception of a user's mistake in inspection's jobs (bad input files, settings or folders)."""


class InspectionError(Exception):
    """A user-facing problem (bad input); the command line prints its message as one line and exits 2."""


def about(path, exc):
    """An :class:`InspectionError` whose message names ``path`` once: ``exc``'s message as it is when it already
    names it (a :class:`datasets.ScanReadError` does), else prefixed with it."""
    message = str(exc)
    return InspectionError(message if str(path) in message else f"{path}: {message}")
