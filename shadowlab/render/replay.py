"""Frame stages traced once per configuration and replayed: Dr.Jit's frozen functions (``dr.freeze``).

A frame stage (the G-buffer with the unshadowed light, a light's views, a wavefront of a virtual
map's tiles, a round of a TOP tree's build on a GPU, ssss's blur passes) is one Dr.Jit kernel or a
few, but tracing it in Python and generating its code can cost more host time than the kernel runs
on a GPU (``shadowlab bench --only frames`` splits a frame into its kernels and host time).
:func:`replayed` traces a stage as usual the first time a configuration is met, records its kernels
the second time and afterwards launches the recorded kernels with the new inputs, skipping the
tracing.

The contract of a stage ``fn(*inputs)`` called through :func:`replayed`:

* every Dr.Jit array it reads comes from ``inputs`` (Dr.Jit arrays, Mitsuba objects such as the
  ``mi.Scene``, and lists, tuples, dicts or dataclasses of them): Dr.Jit refuses to record a stage
  that reads an array made before the call from anywhere else;
* every Python value that shapes its trace (sizes, flags, literals, the scene description) is in
  ``key``: the stage is recorded once per distinct key, and a key already seen replays its recording
  whatever else changed;
* its Mitsuba scene is the one it was recorded with: recordings are kept per ``owner`` (the
  shadowlab Scene whose ``mi_scene`` the stage reads) and forgotten when the owner is collected.
  Replaying a recording with another scene of the same description is what Dr.Jit allows, but with
  drjit 1.5.0 it gave wrong maps and crashes in our tests, so it is not done. A stage that reads no
  Mitsuba object (the tree's rounds, ssss's blurs) has a module-level owner and lives with the
  process. Nor does a
  recording keep its scene alive: every Mitsuba object alive is traced into each call through a
  pointer (a BSDF's ``eval``), so scenes kept for their recordings slowed every later kernel.

Replays give the bits of a fresh trace (the same kernels on the same data; tests/test_replay.py
checks it against the unrecorded stage, for moved light cameras and another scene object too). A
stage whose inputs carry gradients, or called while a frozen function is being recorded, runs
unrecorded. ``SHADOWLAB_REPLAY=0`` turns recording off for the process (every stage traced each
time, as before).
"""

from __future__ import annotations

import os
import weakref
from collections import OrderedDict

import drjit as dr
import numpy as np

#: recorded configurations kept (least recently used dropped first): each holds its kernels
LIMIT = 32
_stages: OrderedDict = OrderedDict()
_failed: set = set()
_owners: dict = {}
_calls: dict = {}   # id(owner) -> its stages' calls through Dr.Jit's frozen function
_DTYPES = {dr.VarType.Float32: np.float32, dr.VarType.Float64: np.float64, dr.VarType.UInt32: np.uint32,
           dr.VarType.Int32: np.int32}


def enabled() -> bool:
    """Recording is on (``SHADOWLAB_REPLAY`` is not ``0``)."""
    return os.environ.get("SHADOWLAB_REPLAY", "1") != "0"


class _Stage:
    """One recorded configuration: a frozen function that calls the stage function of the current
    call (so a re-trace Dr.Jit decides on by itself, e.g. for inputs of another width, traces
    today's inputs and closures, never an earlier call's)."""

    def __init__(self):
        self.fn = None
        self.frozen = dr.freeze(self._call)

    def _call(self, *inputs):
        return self.fn(*inputs)

    def __call__(self, fn, inputs):
        self.fn = fn
        try:
            return self.frozen(*inputs)
        finally:
            self.fn = None


def replayed(name: str, key, fn, owner, *inputs):
    """``fn(*inputs)``, traced as usual the first time (``name``, ``key``, ``owner``) is seen,
    recorded the second time and replayed afterwards (module docstring for the contract; a
    configuration met once, as most are in a comparison, costs no recording). ``key`` must be
    hashable; ``owner`` is the object (the shadowlab Scene) whose lifetime bounds the recording.

    >>> from drjit.llvm import Float
    >>> class Owner: pass
    >>> owner, double = Owner(), (lambda x: x * 2.0)
    >>> [replayed("doctest", (), double, owner, Float(v, 1.0)).numpy().tolist() for v in (1.0, 3.0, 5.0)]
    [[2.0, 2.0], [6.0, 2.0], [10.0, 2.0]]
    >>> recordings("doctest", (), owner)
    1
    >>> del owner; recordings("doctest", (), None)   # forgotten with its owner
    0
    """
    k = (name, key, id(owner))
    if not enabled() or k in _failed or dr.grad_enabled(inputs) or dr.flag(dr.JitFlag.FreezingScope):
        return fn(*inputs)
    stage = _stages.get(k)
    if stage is None:
        if id(owner) not in _owners:
            _owners[id(owner)] = weakref.finalize(owner, _forget, id(owner))
        _stages[k] = _Stage()
        while len(_stages) > LIMIT:
            _stages.popitem(last=False)
        return fn(*inputs)
    _stages.move_to_end(k)
    _calls[id(owner)] = _calls.get(id(owner), 0) + 1
    for attempt in range(2):
        try:
            return stage(fn, inputs)
        except RuntimeError as e:
            if "registry" in str(e) and attempt == 0:
                # objects were registered with Dr.Jit since the recording (another scene loaded), which
                # a recording with calls through pointers cannot replay over: record again
                stage = _stages[k] = _Stage()
                continue
            if "record" not in str(e) and "frozen function" not in str(e):
                raise
            # Dr.Jit cannot record this stage (e.g. it reads an array that is not an input): trace
            # it every time, as without recording (an error of the stage itself is raised again there)
            _failed.add(k)
            _stages.pop(k, None)
            return fn(*inputs)


def _forget(owner_id: int) -> None:
    """Drop the recordings of a collected owner (its id may now be another object's)."""
    _owners.pop(owner_id, None)
    _calls.pop(owner_id, None)
    for k in [k for k in _stages if k[2] == owner_id]:
        del _stages[k]
    for k in [k for k in _failed if k[2] == owner_id]:
        _failed.discard(k)


def uploaded(kind, values):
    """``values`` (numpy or a sequence) as an evaluated Dr.Jit array of ``kind``, made from a Python
    list: with drjit 1.5.0 a stage whose inputs were made from numpy arrays was recorded again on
    some calls and not on others (a copy or a gather of the array did not help), one whose inputs
    came from lists was recorded once.

    >>> from drjit.llvm import Float
    >>> uploaded(Float, [1.0, 2.0]).numpy().tolist()
    [1.0, 2.0]
    """
    out = kind(np.asarray(values, _DTYPES[dr.type_v(kind)]).ravel().tolist())
    dr.eval(out)
    return out


def recordings(name: str, key, owner) -> int:
    """How many times the stage (``name``, ``key``) of ``owner`` has been recorded (0: none kept)."""
    stage = _stages.get((name, key, id(owner)))
    return 0 if stage is None else stage.frozen.n_recordings


def frozen_calls(owner) -> int:
    """How many calls of ``owner``'s stages have gone through Dr.Jit's frozen function (recorded or
    replayed) so far. Each such call walks the variables of every input, the Mitsuba scene's
    registered shapes included, before its kernels run (``shadowlab bench --only frames`` times that
    walk as the scene's replay floor); a stage's first call, traced, is not one.

    >>> from drjit.llvm import Float
    >>> class Owner: pass
    >>> owner = Owner()
    >>> for v in (1.0, 2.0, 3.0): _ = replayed("doctest_calls", (), lambda x: x + 1.0, owner, Float(v))
    >>> frozen_calls(owner)
    2
    """
    return _calls.get(id(owner), 0)


def clear() -> None:
    """Forget every recording (the next call of each stage traces it again)."""
    _stages.clear()
    _failed.clear()
