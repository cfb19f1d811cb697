"""One error family for shadowlab; each error carries the CLI exit code it maps to.

Exit codes (docs/ARCHITECTURE.md, Conventions; the README's exit-code paragraph): 0 ok, 1 a gate
failed, 2 bad input or usage, 3 environment (no usable libLLVM, missing package, a file that
cannot be written, out of memory), 4 an internal error (a shadowlab bug: a short "please report"
line, the traceback only with ``SHADOWLAB_DEBUG=1``), 130 interrupted by SIGINT (Ctrl-C), 143
terminated by SIGTERM.
"""

import signal

#: exit code of an unexpected exception inside shadowlab (a bug)
INTERNAL_ERROR = 4


class ShadowlabError(Exception):
    """Base class. ``str(err)`` is a message that names the problem and the fix."""

    exit_code = 2


class InputError(ShadowlabError):
    """Bad input: a scene, image, parameter or file the user gave us is wrong."""

    exit_code = 2


class SceneError(InputError):
    """A scene file is missing or malformed. The message names the file and the key."""


class ReferenceError_(InputError):
    """A stored reference is missing, stale or would be overwritten without --force."""


class EnvironmentProblem(ShadowlabError):
    """The machine cannot run shadowlab as is (libLLVM, a package); the message says what to install."""

    exit_code = 3


class GateFailure(ShadowlabError):
    """A gate ran and the candidate failed it."""

    exit_code = 1


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived (raised by the CLI's signal handler). A ``BaseException``, like
    ``KeyboardInterrupt``: ``except Exception`` does not swallow it, while the ``except
    BaseException: clean up; raise`` blocks of the atomic writers remove what they had begun.
    The exit code is 128 + the signal number (130 for SIGINT, 143 for SIGTERM); ``detail`` is what
    the command left behind, for the one line the CLI prints (a callable: read when the line is
    printed, after the command has closed what it opened)."""

    def __init__(self, signum: int, detail: str = ""):
        super().__init__(signum, detail)
        self.signum = int(signum)
        self.detail = detail

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    @property
    def signal_name(self) -> str:
        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"
