"""One error family for shadowlab; each error carries the CLI exit code it maps to.

Exit codes (docs/ARCHITECTURE.md, Conventions): 0 ok, 1 a gate failed, 2 bad input or usage,
3 environment (no usable libLLVM, missing package).
"""


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
