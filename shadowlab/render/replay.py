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

What Dr.Jit walks at each call. A frozen function walks the variables of every input at each call,
before its kernels and again after them, and a Mitsuba scene among them is costly: walking it walks
every shape, emitter and sensor it holds, and its arrays of shape pointers then make Dr.Jit walk
every object registered with it again. :func:`replayed` therefore gives Dr.Jit, for a Mitsuba scene
among the inputs, what a stage reads of it (:func:`_walked`): the scene's acceleration structure
handles and the shapes, emitters and sensors of the scenes read, each walked once. A stage whose
kernels read more (Dr.Jit refuses to record it) is recorded with the whole scene.

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
import mitsuba as mi
import numpy as np

#: recorded configurations kept (least recently used dropped first): each holds its kernels
LIMIT = 32
_stages: OrderedDict = OrderedDict()
_failed: set = set()
_owners: dict = {}
_calls: dict = {}   # id(owner) -> its stages' calls through Dr.Jit's frozen function
_whole: set = set()  # stages recorded with their whole Mitsuba scene (they read more than _walked gives)
_objects: dict = {}  # (id(owner), id(mi scene)) -> its shapes, emitters and sensors, for every scene read
#: the variables of Mitsuba's acceleration structure, the first its Scene walks (mitsuba 3.9's
#: ``EmbreeAccel``: the Embree scene, its two entry points, the shapes' registry ids; ``OptixAccel``:
#: the OptiX scene and its shader binding table), by backend
_ACCEL = {"llvm": ("UInt64", "UInt64", "UInt64", "UInt32"), "cuda": ("UInt64", "UInt64")}
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
    _note_scenes(inputs, owner)
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
    scenes = any(isinstance(x, mi.Scene) for x in inputs)
    retried = False
    while True:
        whole = k in _whole or not scenes
        try:
            return stage(fn, inputs if whole else _walked(inputs))
        except RuntimeError as e:
            if "record" in str(e) and not whole:
                # its kernels read more of the scene than _walked gives (e.g. another scene's shapes,
                # registered too, enter its calls through pointers): record it with the whole scene
                _whole.add(k)
                stage = _stages[k] = _Stage()
                continue
            if "registry" in str(e) and not retried:
                # objects were registered with Dr.Jit since the recording (another scene loaded), which
                # a recording with calls through pointers cannot replay over: record again
                retried = True
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
    for done in (_failed, _whole):
        for k in [k for k in done if k[2] == owner_id]:
            done.discard(k)
    for k in [k for k in _objects if k[0] == owner_id]:
        del _objects[k]


def _note_scenes(inputs, owner) -> None:
    """Keep the objects of each Mitsuba scene among ``inputs`` while ``owner`` lives (:func:`_walked`)."""
    for x in inputs:
        if isinstance(x, mi.Scene) and (id(owner), id(x)) not in _objects:
            _objects[(id(owner), id(x))] = [list(x.shapes()), list(x.emitters()), list(x.sensors())]


def _walked(inputs) -> tuple:
    """``inputs`` with each Mitsuba scene replaced by what a stage reads of it: its acceleration
    structure's arrays (:func:`accel_arrays`) and the objects of every scene the stages of a live
    owner read. A call through a pointer (a shape's intersection, a BSDF's evaluation) traces every
    object registered with Dr.Jit, so each of theirs must be an input too; an object of no such
    scene makes Dr.Jit refuse the recording (:func:`replayed` then records the whole scene)."""
    objects = list(_objects.values())
    return tuple([accel_arrays(x), objects] if isinstance(x, mi.Scene) else x for x in inputs)


class _Enough(Exception):
    """Ends a walk of a scene's variables once the acceleration structure's are found."""


class _Arrays:
    """Holds the acceleration structure's arrays while Dr.Jit points them at the scene's variables."""


def accel_arrays(mi_scene) -> list:
    """The variables of ``mi_scene``'s acceleration structure (:data:`_ACCEL`), as Dr.Jit arrays that
    refer to them: what a ray query reads of the scene itself, besides its shapes. Taken anew at every
    call (the first entries of the scene's walk), so a rebuilt structure is never missed.

    >>> import mitsuba as mi
    >>> scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere"}})
    >>> [type(a).__name__ for a in accel_arrays(scene)] == [t.__name__ for t in _accel_types()]
    True
    """
    types = _accel_types()
    found = []

    def visit(index, variant, domain):
        found.append(index)
        if len(found) == len(types):
            raise _Enough

    try:
        with dr.scoped_set_flag(dr.JitFlag.EnableObjectTraversal, True):
            mi_scene._traverse_1_cb_ro(visit)
    except _Enough:
        pass
    holder = _Arrays()
    holder.__dict__.update({f"a{i}": t(0) for i, t in enumerate(types[:len(found)])})
    it = iter(found)
    dr.detail.traverse_py_cb_rw(holder, lambda index, variant, domain: next(it))
    return list(holder.__dict__.values())


def _accel_types() -> list:
    """The Mitsuba array types of :data:`_ACCEL` for the current variant's backend."""
    return [getattr(mi, t) for t in _ACCEL["cuda" if mi.variant().startswith("cuda") else "llvm"]]


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
    shapes included, before its kernels run (``shadowlab bench --only frames`` times that
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
    _whole.clear()
    _objects.clear()
