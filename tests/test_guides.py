"""Guides between views (method/guides.py): earlier views' proposals reprojected into a view, nearest first; for
ink, what earlier views painted on the splats; and the loop's guided proposals agreeing across views better than
unguided ones."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_pipeline import TINY, away_camera, ring_cameras, sphere_scene, textured_style

from dresg_addon.method.color_solve import ColorSolveSettings, LinearViews, ViewsInTurn
from dresg_addon.method.guides import PAINTED_SHARE, painted_guide, view_guide
from dresg_addon.method.loop import stylize
from dresg_addon.raster import ColorOnlyRenderer, geometry_tensors, render_scene
from dresg_addon.scene.warp import warp_to


def renders(scene, cameras):
    out = [render_scene(scene, camera) for camera in cameras]
    return [o.depth for o in out], [o.alpha for o in out]


def test_a_view_seen_from_the_same_camera_is_its_own_guide():
    scene, camera = sphere_scene(), ring_cameras(3)[0]
    cameras = [camera, camera]
    depths, alphas = renders(scene, cameras)
    y, x = torch.meshgrid(torch.linspace(0, 1, 16), torch.linspace(0, 1, 24), indexing="ij")
    proposal = torch.stack([x, y, x * y])  # smooth, at half the camera's size
    image, weight = view_guide(1, [0], [proposal, None], depths, alphas, cameras, 3.0)
    assert image.shape == (3, 16, 24) and weight.shape == (16, 24)
    covered = torch.nn.functional.interpolate((alphas[0] > 0.5).float()[None, None], size=(16, 24))[0, 0] > 0
    inner = weight == 3.0
    assert inner.sum() > 0.5 * covered.sum() and float(weight.max()) == 3.0 and float(weight.min()) == 0.0
    assert float((image - proposal)[:, inner].abs().mean()) < 0.02  # resampled twice, otherwise the same
    assert view_guide(1, [], [proposal, None], depths, alphas, cameras, 3.0) is None
    assert view_guide(1, [0], [proposal, None], depths, alphas, cameras, 0.0) is None


def test_the_nearest_earlier_view_wins_and_what_no_earlier_view_sees_has_no_weight():
    scene = sphere_scene()
    ring = ring_cameras(12)
    cameras = [ring[3], ring[1], ring[0]]  # view 2's nearest earlier view is view 1
    depths, alphas = renders(scene, cameras)
    red, blue = torch.zeros(3, 32, 48), torch.zeros(3, 32, 48)
    red[0], blue[2] = 1.0, 1.0
    image, weight = view_guide(2, [0, 1], [red, blue, None], depths, alphas, cameras, 2.0)
    _, both = warp_to(torch.zeros(32, 48, 3), depths[0], cameras[0], cameras[2], depths[2], alphas[0], alphas[2])
    _, near = warp_to(torch.zeros(32, 48, 3), depths[1], cameras[1], cameras[2], depths[2], alphas[1], alphas[2])
    both &= near
    assert both.sum() > 20
    assert float(image[2][both].mean()) > 0.95 and float(image[0][both].mean()) < 0.05
    assert float(weight[alphas[2] < 0.5].max()) == 0.0  # the background gets no guide
    away = [ring[0], away_camera()]
    depths, alphas = renders(scene, away)
    assert view_guide(1, [0], [red, None], depths, alphas, away, 2.0) is None  # it sees nothing of the sphere


def test_a_painted_guide_shows_what_earlier_views_painted_where_their_splats_cover_the_pixel():
    scene, cameras = sphere_scene(), ring_cameras(12)[:2]  # two neighbouring views of one sphere
    renderers = [ColorOnlyRenderer(*geometry_tensors(scene), camera) for camera in cameras]
    views = LinearViews([r.linear_map() for r in renderers], [r.background for r in renderers])
    turn = ViewsInTurn(views, 0.5, ColorSolveSettings())
    assert painted_guide(turn, 1, cameras[1], (16, 24), 4.0) is None  # nothing painted yet
    stripes = torch.zeros(3, cameras[0].height, cameras[0].width)
    stripes[:, :, (torch.arange(cameras[0].width) // 6) % 2 == 0] = 1.0  # white bands 6 px wide, on black
    turn.paint(0, stripes)
    guide = painted_guide(turn, 1, cameras[1], (cameras[1].height, cameras[1].width), 4.0)
    assert guide is not None
    image, weight = guide
    assert image.shape == (3, cameras[1].height, cameras[1].width) and set(weight.unique().tolist()) <= {0.0, 4.0}
    _, share = turn.painted_image(1)
    share = share.reshape(cameras[1].height, cameras[1].width)
    assert torch.equal(weight > 0, share >= PAINTED_SHARE) and int((weight > 0).sum()) > 50
    # The guide is the painted splats' render: in view 0 itself it gives the stripes back where it is guided.
    own, own_weight = painted_guide(turn, 0, cameras[0], (cameras[0].height, cameras[0].width), 4.0)
    inner = (own_weight > 0) & (renderers[0].alpha > 0.99)
    assert int(inner.sum()) > 50
    drawn, wanted = own[0][inner], stripes[0][inner]
    assert float(torch.corrcoef(torch.stack([drawn, wanted]))[0, 1]) > 0.7  # the stripes, as far as splats draw them
    assert float(drawn.std()) > 0.25  # bands, not grey
    assert painted_guide(turn, 1, cameras[1], (16, 24), 0.0) is None


@pytest.mark.slow
def test_guided_proposals_agree_across_views_better_than_unguided_ones(monkeypatch):
    from dresg_addon.method.medium import Paint

    scene, cameras = sphere_scene(n=600), ring_cameras(6)
    depths, alphas = renders(scene, cameras)
    config = TINY.with_(stages=1, post_steps=0, proposal_width=48, proposal_height=32)

    def disagreement(guide_weight: float) -> float:
        monkeypatch.setattr(Paint, "guide_weight", guide_weight)
        updates = []
        stylize(scene, cameras, textured_style(32, 48), config.config, plan=config.plan, on_stage=updates.append)
        proposals = [torch.from_numpy(updates[0].images[c.name]["proposal"]) for c in cameras]
        errors = []
        for i in range(len(cameras) - 1):
            warped, valid = warp_to(
                proposals[i], depths[i], cameras[i], cameras[i + 1], depths[i + 1], alphas[i], alphas[i + 1]
            )
            errors.append(float((warped - proposals[i + 1]).square().sum(-1)[valid].mean()))
        return float(np.sqrt(np.mean(errors)))

    assert disagreement(4.0) < 0.8 * disagreement(0.0)
