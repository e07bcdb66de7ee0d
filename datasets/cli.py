"""What the toolkit's command lines share: an argument parser whose mistakes are one line, and one-line messages.

Every user mistake on a command line (``nsspr-data``, ``nsspr-train``, ``nsspr-inspect``, ``nsspr-field``) is one
line on stderr, ``error: ...``, and exit status 2, never a traceback or argparse's usage block. Only argparse is
imported here, so ``--help`` stays fast.
"""
import argparse


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line on stderr (``error: ... (see PROG --help)``, then exit
    status 2), like every other user mistake, instead of the usage block followed by the error. Its sub-parsers are
    of the same class."""

    def error(self, message):
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def one_line(exc):
    """The message of a user-facing error as one line: an OSError names its file first, then the reason; a
    KeyError's quotes are dropped; an empty message is the exception's type."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    text = " ".join(str(exc).split())
    if isinstance(exc, KeyError):
        text = text.strip("'\"")
    return text or type(exc).__name__
