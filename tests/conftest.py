"""Shared fixtures. Tests that run Mitsuba ask for ``mitsuba_backend`` (once per session);
tests that do not need Mitsuba never initialise it. ``frame_of`` shares the frames of built-in
scenes across the session. Scene documents, TOML and frames of inline scenes: tests/scene_builder.py.

The ``slow`` marker (pyproject.toml) is given here, in one place, to every test of the files in
:data:`SLOW_FILES` and to the tests in :data:`SLOW_TESTS` (by ``pytest_collection_modifyitems``),
not by ``pytestmark`` lines or decorators in the files:
several of them belong to other work in progress, and the list is easier to re-measure as a whole.
``make test-fast`` runs ``-m "not slow"`` while editing, ``make test`` runs everything."""

import importlib.metadata
import os

import pytest

#: the variant this session runs (the ``mitsuba_backend`` fixture selects the same one)
VARIANT = os.environ.get("SHADOWLAB_VARIANT") or "llvm_ad_rgb"
CUDA = VARIANT.startswith("cuda")


def llvm_only(reason: str):
    """Skip a test under ``cuda_ad_rgb``, saying why it holds only for the LLVM backend."""
    return pytest.mark.skipif(CUDA, reason=f"llvm_ad_rgb only: {reason}")


#: the gate plugin is found through the package's ``pytest11`` entry point: a checkout on
#: ``PYTHONPATH`` that was never pip-installed (the GPU machine's bundle, DEVELOPERS.md) has none
plugin_installed = pytest.mark.skipif(
    not any(ep.value.startswith("shadowlab") for ep in importlib.metadata.entry_points(group="pytest11")),
    reason="shadowlab is not pip-installed here, so pytest has no shadowlab plugin entry point")


#: Test files whose tests are all marked ``slow``: seconds (setup + call + teardown, summed per file)
#: of one full run, ``pytest --durations=0``, 885 tests on 2 cores shared with another full run, so
#: about 1.5 to 2.6 times what they take alone. A file is here when its time per test was over
#: ~1.1 s. To re-measure: one full run with ``--durations=0``, sum per file, keep the files with the
#: most seconds per test; then time ``-m "not slow" --durations=0`` and fill :data:`SLOW_TESTS`.
SLOW_FILES = {
    "test_gate_plugin.py": 262,         # 8 tests
    "test_gate.py": 218,                # 43 tests
    "test_ssss_many.py": 101,           # 8 tests
    "test_ingest.py": 73,               # 11 tests
    "test_fit_multilight.py": 67,       # 4 tests
    "test_fit.py": 64,                  # 14 tests
    "test_cli_reliability.py": 55,      # 19 tests
    "test_fit_scenes.py": 50,           # 8 tests
    "test_moments.py": 48,              # 15 tests
    "test_frames.py": 34,               # 18 tests
    "test_distributed.py": 31,          # 12 tests
    "test_ssss.py": 30,                 # 16 tests
    "test_light_kinds.py": 29,          # 8 tests
    "test_store_and_cli.py": 29,        # 12 tests
    "test_bench_virtual.py": 28,        # 8 tests
    "test_lightview_fits.py": 26,       # 14 tests
    "test_sdf_trace.py": 26,            # 13 tests
    "test_truth_allocation.py": 25,     # 4 tests
    "test_bench_dpsv.py": 23,           # 9 tests
    "test_pcss.py": 22,                 # 18 tests
    "test_cascades_measures.py": 22,    # 3 tests
    "test_pcf_kernels.py": 21,          # 19 tests
    "test_api.py": 19,                  # 8 tests
    "test_report_tiles.py": 17,         # 8 tests
    "test_alpha.py": 14,                # 8 tests
    "test_backend.py": 12,              # 4 tests
    "test_sweep.py": 7,                 # 6 tests
    "test_report_browser.py": 7,        # 4 tests
    "test_architecture_example.py": 6,  # 1 test
    "test_pcf_acne.py": 4,              # 2 tests
    "test_wheel.py": 28,                # 2 tests: builds, installs and runs the wheel
    "test_casts_shadows.py": 22,        # 7 tests (CPU seconds; every technique on two scenes)
    "test_applicability.py": 20,        # 6 tests: compare -t all and fit --all through the CLI
    "test_light_mix.py": 25,            # 6 tests: techniques per light on two_lights and many_lights, a fit
    "test_suggested_commands.py": 13,   # 1 test: reference, fit and the pasted compare through the CLI
    "test_engines.py": 64,              # 13 tests: three.js and Babylon.js in headless Chromium
    "test_reliability_scheduler.py": 45,  # 7 tests: real shadowlab processes against silent or foreign servers
    "test_reliability_interrupt.py": 27,  # 1 test: Ctrl-C of a real reference --workers 2
}


#: Single tests marked ``slow`` in the other files: the calls of 1.5 s or more in one run of the
#: ``-m "not slow"`` set on an otherwise idle machine (seconds of the call; their module fixtures
#: are cheap, so marking them moves no setup cost onto the next test). Key: ``file::test[params]``.
SLOW_TESTS = {
    "test_docs.py::test_docs_site_builds_without_warnings": 8.6,
    "test_export.py::test_export_cli": 6.5,
    "test_doctests.py::test_docstring_examples[shadowlab.api]": 5.3,
    "test_sdf_field.py::test_csg_and_nonuniform_scale_are_bounds_of_the_true_distance": 5.0,
    "test_architecture.py::test_a_forbidden_import_is_found": 4.9,
    "test_translucent.py::test_ssss_colour_is_the_product_of_transmittances": 4.7,
    "test_cascades.py::test_stable_cascades_do_not_shimmer_under_a_sub_texel_move_the_box_fit_does": 3.6,
    "test_technique_contract.py::test_pcss_light_scale_scales_every_light_by_its_own_size": 3.4,
    "test_dpsv.py::test_soft_penumbra_has_the_same_world_width_from_any_camera_distance": 2.9,
    "test_sdf_truth.py::test_mandelbulb_mc_reproduces_its_reference_and_the_single_ray_leaks": 2.7,
    "test_virtual_maps.py::test_the_cli_refuses_a_bad_t_max_with_exit_2_and_no_traceback": 2.6,
    "test_outdoor_scenes.py::test_committed_street_reference_loads_and_hard_compares": 2.3,
    "test_dpsv.py::test_fused_equals_exact_except_the_classifiers_misses[point]": 2.2,
    "test_translucent.py::test_light_view_stores_opaque_depth_and_the_casters_colour": 2.1,
    "test_default_acne.py::test_defaults_leave_no_acne_on_a_flat_shaded_mesh[hard]": 2.0,
    "test_techniques_shadow_map.py::test_each_bias_variant_removes_most_acne": 2.0,
    "test_sdf_field.py::test_exact_primitives_agree_with_brute_force_distance[box-sdf0]": 1.9,
    "test_techniques_shadow_map.py::test_hard_equals_exact_point_light_visibility_up_to_edge_aliasing": 1.9,
    "test_cascades.py::test_the_report_colours_the_cascades": 1.9,
    "test_store_faults.py::test_two_writers_creating_one_reference_one_wins_the_other_exits_2": 1.8,
    "test_export.py::test_shadow_camera_is_the_map_hard_samples": 1.6,
    "test_reliability_exits.py::test_out_on_a_mount_point_of_its_own_is_written": 16.1,
    "test_reliability_exits.py::test_a_report_on_a_full_disk_exits_3": 14.7,
    "test_reliability_exits.py::test_out_across_devices_in_process": 13.6,
    "test_reliability_vacuous.py::test_on_a_cluster_the_refusal_is_one_line_without_a_dask_dump": 14.2,
    "test_reliability_messages.py::test_the_same_scene_twice_is_refused_before_any_work[dask]": 6.0,
    "test_reliability_messages.py::test_a_reader_during_a_swap_waits_for_the_new_reference": 8.0,
}


def pytest_collection_modifyitems(config, items):
    """Mark ``slow`` every test of a file in :data:`SLOW_FILES` and every test in :data:`SLOW_TESTS`."""
    slow = pytest.mark.slow
    for item in items:
        if item.path.name in SLOW_FILES or f"{item.path.name}::{item.name}" in SLOW_TESTS:
            item.add_marker(slow)


@pytest.fixture(scope="session")
def mitsuba_backend():
    """Select the Mitsuba variant (llvm_ad_rgb unless $SHADOWLAB_VARIANT) once; return its name."""
    from shadowlab import backend
    return backend.init()


@pytest.fixture(scope="session")
def dask_workers(mitsuba_backend):
    """A real Dask LocalCluster of 2 worker processes (one task thread each), shared by the
    distributed tests of a session: an executor from :func:`shadowlab.cluster.open_executor`."""
    from shadowlab.cluster import open_executor
    with open_executor(workers=2) as ex:
        yield ex


@pytest.fixture(scope="session")
def frame_of(mitsuba_backend):
    """A factory ``frame_of(name, resolution=None, *, seed=0, u_strata=16, ss=1)``: the FrameContext of
    built-in scene ``name`` (``make_frame(load(name, resolution), ss=ss, u_strata=u_strata, seed=seed)``),
    made once per session per arguments and then shared by every test that asks for it.

    Only for tests that read the frame: rendering techniques on it is fine (the light views it casts
    on demand are cached in the frame by their full key, so the same map is reused), but a test that
    changes the frame's G-buffer, unshadowed light or caches must make its own with ``make_frame``,
    and so must one that counts the kernels a render launches (another test may have rendered there first).
    The defaults are ``make_frame``'s (16 strata of U_L); most tests of techniques pass ``u_strata=1``."""
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load

    frames = {}

    def frame_of(name: str, resolution=None, *, seed: int = 0, u_strata: int = 16, ss: int = 1):
        res = None if resolution is None else tuple(int(x) for x in resolution)
        key = (name, res, int(seed), int(u_strata), int(ss))
        if key not in frames:
            frames[key] = make_frame(load(name, resolution=res), ss=int(ss), u_strata=int(u_strata), seed=int(seed))
        return frames[key]

    return frame_of
