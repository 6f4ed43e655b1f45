# SPDX-License-Identifier: Apache-2.0
"""What the gp-ground-seg tools raise for bad input, and how it reaches the user.

Every expected failure (a missing file, a corrupt bag, a bad option) is shown as one line,
``gp-ground-seg <cmd>: error: ...`` on stderr, with exit status :data:`EXIT_ERROR`; anything
else is a bug and keeps its traceback.
"""

from __future__ import annotations

from rosbags.highlevel import AnyReaderError
from rosbags.rosbag1 import ReaderError as Reader1Error
from rosbags.rosbag2 import ReaderError as Reader2Error, WriterError

EXIT_ERROR = 2  # argparse's status for a usage error; every expected failure uses it


class CliError(Exception):
    """An expected failure with a one-line message (exit status 2)."""


class BagError(ValueError):
    """A bag or point-file input/output problem, described in one line."""


# Exceptions that mean bad input or environment, not a bug: reported in one line. rosbags'
# own errors are here because a truncated bag or an unwritable output raises them.
EXPECTED_ERRORS = (CliError, ValueError, OSError, EOFError, AnyReaderError, Reader1Error,
                   Reader2Error, WriterError)


def one_line(err: BaseException, limit: int = 400) -> str:
    """``err`` as one line of at most ``limit`` characters (its type name if it has no text)."""
    text = ' '.join(str(err).split()) or type(err).__name__
    return text if len(text) < limit else text[:limit - 3] + '...'
