"""Shared fixtures: the real third-party data in ../shared/data (tests skip when it is absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Tests compare runs bit for bit: keep torch's thread count fixed (tests/test_threads.py turns it back on).
os.environ.setdefault("DRESG_ADAPTIVE_THREADS", "0")

SHARED_DATA = Path(os.environ.get("DRESG_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_file(relative: str) -> Path:
    """Path of a file in ../shared/data; skips the test when it is not there."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"shared data not present: {path}")
    return path


@pytest.fixture
def shared_data():
    return shared_file


@pytest.fixture
def addon():
    """The extension registered in a clean, empty Blender file (bpy module); unregistered afterwards."""
    bpy = pytest.importorskip("bpy")
    import stylize_headless  # scripts/, on pytest's pythonpath

    bpy.ops.wm.read_factory_settings(use_empty=True)
    module = stylize_headless.load_addon()
    yield module
    module.unregister()  # cancels and forgets the jobs


# The unit loop, `python -m pytest -q -m unit`: the quick engine tests to run between edits (under 30 s on
# 2 cores). Whole files less the tests named here (their heavier runs, real data, subprocesses, bpy), chosen
# by measured duration; parametrized cases go with their test's name. The rest stays in the fast loop.
UNIT_LEAVES_OUT = {
    "test_artist_controls.py": {
        "test_a_run_says_when_the_splats_are_wider_than_the_strokes",
        "test_projected_mean_variance_is_the_projections_covariance_trace",
    },
    "test_backends.py": {"test_the_synth_backend_gets_the_same_settings_and_proposes_the_same_pixels"},
    "test_bad_input.py": set(),
    "test_cameras.py": {
        "test_blender_projection_matches_view_plane",
        "test_blender_round_trip_identity",
        "test_blender_conversion_matches_bpy",
    },
    "test_cli_options.py": {
        "test_the_same_spelling_gives_the_same_value_everywhere",
        "test_the_same_bad_spelling_gives_the_same_one_line_error_everywhere",
    },
    "test_cli_scene.py": {"test_python_m_info_subprocess", "test_info_on_real_files"},
    "test_color_solve.py": {
        "test_targets_a_scene_can_show_are_reached_as_the_dense_least_squares_solution_does",
        "test_targets_outside_what_the_box_allows_reach_the_bounded_optimum",
        "test_views_in_turn_hold_what_earlier_views_painted_and_reach_targets_that_agree",
        "test_fit_split_by_splat_width_separates_disagreeing_views_from_what_no_view_can_draw",
        "test_best_views_keep_the_joint_fit_where_the_views_agree_and_each_views_marks_where_they_do_not",
        "test_more_iterations_fit_closer",
        "test_the_first_view_leaves_splats_no_view_draws_alone_and_refuses_a_share_outside_0_1",
    },
    "test_color_transfer.py": set(),
    "test_config.py": {"test_a_checkpoint_of_an_earlier_version_starts_over_in_one_line_naming_it"},
    "test_fuzz.py": {"test_writes_at_random_size_limits_complete_or_fail_cleanly"},
    "test_guides.py": set(),
    "test_imageio.py": set(),
    "test_io.py": {"test_convert_real_splat_to_compressed_and_back", "test_real_compressed_ply_matches_the_splat_file"},
    "test_losses.py": {"test_ssim_gradcheck_float64", "test_ssim_matches_the_2d_window_formulation"},
    "test_metrics.py": {  # the sliced Wasserstein distance keeps its known cases
        "test_texture_kept_and_shapes_of_an_image_against_itself_are_1",
        "test_clip_style_score",
        "test_dino_content_score",
        "test_model_errors",
        "test_sw_colors_identical_zero_and_shift_grows",
        "test_sw_colors_list_of_sizes_and_subsampling",
        "test_sw_colors_masked_is_the_sw_of_the_covered_pixels",
        "test_sw_colors_deterministic_and_seeded",
        "test_sw_flat_images_are_finite",
        "test_sw_patches_masked_ignores_windows_touching_the_background",
        "test_float_alpha_masks_threshold_at_half",
        "test_masks_that_cover_nothing_fall_back_to_all_pixels",
        "test_texture_replaced_by_noise_is_not_kept_but_the_shapes_are",
        "test_texture_kept_and_shapes_of_flat_images_are_defined",
    },
    "test_optim.py": set(),
    "test_pcgrad.py": set(),
    "test_proposal_synth.py": {
        "test_propose_on_stiff_inputs",
        "test_real_photo_takes_the_painting_texture",
        "test_stroke_size_scales_the_marks",
        "test_a_stage_for_another_style_falls_back_to_per_view_colours",
        "test_prepare_stage_fits_one_colour_map_for_every_view",
        "test_a_fine_checker_in_the_content_does_not_reach_a_proposal_of_a_smooth_painting",
        "test_propose_is_seeded_and_reports_one_energy_per_update",
        "test_a_guide_holds_the_synthesis_to_it_where_it_has_weight",
        "test_a_final_match_gives_a_coarse_stage_the_paintings_palette_at_full_resolution",
        "test_a_proposal_holds_the_scenes_shading_with_light_weight",
        "test_propose_never_paints_the_background",
    },
    "test_raster.py": {
        "test_one_by_one_and_4096_images_stay_sparse",
        "test_real_luigi_matches_reference",
        "test_real_bonsai_window_matches_reference",
    },
    "test_schedule.py": {"test_betas_and_alpha_bar_match_diffusers"},
    "test_targets.py": set(),
    "test_up_axis.py": set(),
    "test_views.py": set(),
}
# Files of long runs where the loop takes only the tests named here: one short run of the whole loop and
# the checks it makes before any work.
UNIT_TAKES_ONLY = {
    "test_pipeline.py": {
        "test_one_active_view_runs_without_gradient_projection",
        "test_attention_ablations_are_refused_for_the_synth_backend",
        "test_cameras_that_see_nothing_are_an_error",
        "test_bad_style_arrays_are_refused",
        "test_stage_improvement_is_the_drop_over_the_window",
        "test_pixel_widths_are_the_splats_screen_sigma_where_drawn_and_zero_elsewhere",
    },
}


@pytest.hookimpl(tryfirst=True)  # before -m selects by marker
def pytest_collection_modifyitems(items):
    for item in items:
        name, test = item.path.name, getattr(item, "originalname", item.name)
        if "slow" in item.keywords or "blender" in item.keywords:
            continue
        if test not in UNIT_LEAVES_OUT.get(name, {test}) or test in UNIT_TAKES_ONLY.get(name, ()):
            item.add_marker(pytest.mark.unit)


def pytest_ignore_collect(collection_path, config):
    """With -m unit, test files without a unit test are not imported: several import bpy, diffusers or
    matplotlib, which alone would take longer than the loop's tests."""
    if config.getoption("markexpr") != "unit" or collection_path.suffix != ".py":
        return None
    name = collection_path.name
    if name.startswith("test_") and name not in UNIT_LEAVES_OUT and name not in UNIT_TAKES_ONLY:
        return True
    return None
