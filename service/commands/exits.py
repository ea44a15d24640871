"""The exit codes every ``inspection`` command keeps, and the error that asks for code 2.

A script driving the line reads the same code from every command:

- 0: done, and what was measured passed;
- 1: measured, and it did not pass (a part that fails or cannot be judged,
  a cloud that does not match its CAD, a fit that is not usable, a replay
  that differs);
- 2: bad input or usage (a missing, empty, malformed or corrupt file, a
  directory where a file belongs, a bad option or config): one line on
  stderr, never a traceback;
- 3: an internal error (a defect of ours): one line on stderr, the
  traceback only with ``-vv``.

130 is an interruption (Ctrl-C), as shells report it.
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERNAL = 3
EXIT_INTERRUPTED = 130

EPILOG = """\
exit codes (the same for every command):
  0  done, and what was measured passed
  1  measured, and it did not pass (fails, not measurable, no match to the CAD,
     a replay that differs)
  2  bad input or usage: a missing, empty, malformed or corrupt file, a directory
     where a file belongs, a bad option or config (one line on stderr)
  3  internal error (one line on stderr; -vv shows the traceback)
"""


class BadInput(Exception):
    """Input the command cannot work with; the CLI prints the message and exits 2."""
