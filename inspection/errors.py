"""The one exception of a user's mistake in inspection's jobs (bad input files, settings or folders)."""


class InspectionError(Exception):
    """A user-facing problem (bad input); the command line prints its message as one line and exits 2."""
