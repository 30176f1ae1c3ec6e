"""The fast preview renderer against closed forms (no Mitsuba)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from dynbtf.render.preview import (DirectionalLight, PinholeCamera, PointLight, grazing_camera, render_preview,
                                   top_camera)
from dynbtf.representations.base import Representation


class Probe:
    """A "BTF" that reports its inputs: R = w_view.z, G = w_light.z, B = frac(u)."""

    def eval(self, uv, w_view, w_light):
        return np.stack([w_view[:, 2], w_light[:, 2], uv[:, 0] - np.floor(uv[:, 0])], -1)


class ConstantAlbedo(Representation):
    """A Lambertian test representation: value = albedo everywhere (pi f_r = albedo)."""

    def __init__(self, albedo):
        super().__init__()
        self.register_buffer("plane", torch.zeros(8, 8, 1))
        self.register_buffer("albedo", torch.tensor(albedo, dtype=torch.float32))

    def positional_plane(self):
        return self.plane

    def decode(self, features, w_view, w_light):
        return self.albedo.expand(*features.shape[:-1], 3)

    def config(self):
        return {"albedo": self.albedo.tolist()}


def _top_view_points(res, extent, center, distance):
    """World hit points of pixel centres of ``top_camera`` derived by hand: u right, v up."""
    half = extent / 2.0
    s = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    x = center[0] + s[None, :] * half * np.ones((res, 1))
    y = center[1] - s[:, None] * half * np.ones((1, res))
    return np.stack([x, y, np.zeros_like(x)], -1)


def test_lambertian_under_point_light_matches_inverse_square_cosine_law():
    from dynbtf.synthesized import synthesized_btf

    albedo = [0.8, 0.5, 0.25]
    btf = synthesized_btf(ConstantAlbedo(albedo), "tile")
    res, extent, center, distance = 33, 4.0, (0.3, -0.2), 5.0
    light = PointLight(position=(1.0, 0.5, 1.5), intensity=3.0)
    img = render_preview(btf, top_camera(extent, center, distance), light, resolution=(res, res))
    p = _top_view_points(res, extent, center, distance)
    to_light = np.array(light.position) - p
    r = np.linalg.norm(to_light, axis=-1)
    expected = np.array(albedo) * (to_light[..., 2] / r * light.intensity / r ** 2)[..., None]
    np.testing.assert_allclose(img, expected, rtol=2e-5, atol=1e-6)
    assert img.max() > 0.3  # a visible, non-trivial gradient
    assert img[..., 0].std() > 0.05


def test_directions_and_uv_reach_the_btf_as_derived_by_hand():
    res, extent, center, distance = 21, 2.0, (3.25, 1.5), 4.0
    light = DirectionalLight(direction=(0.0, 0.6, 0.8), irradiance=1.0)
    img = render_preview(Probe(), top_camera(extent, center, distance), light, resolution=(res, res))
    p = _top_view_points(res, extent, center, distance)
    to_cam = np.array([center[0], center[1], distance]) - p
    wv_z = to_cam[..., 2] / np.linalg.norm(to_cam, axis=-1)
    cos_l = 0.8
    np.testing.assert_allclose(img[..., 0], wv_z * cos_l, rtol=1e-5)
    np.testing.assert_allclose(img[..., 1], cos_l * cos_l, rtol=1e-5)
    np.testing.assert_allclose(img[..., 2], (p[..., 0] - np.floor(p[..., 0])) * cos_l, rtol=1e-4, atol=1e-5)


def test_grazing_view_shows_sky_above_the_analytic_horizon_row():
    res = 64
    cam = grazing_camera(distance=6.0, height=0.6, fov=40.0)
    img = render_preview(Probe(), cam, DirectionalLight((0, 0, 1), 1.0), resolution=(res, res),
                         background=(-1.0, -1.0, -1.0))
    sky_rows = int((img[:, res // 2, 0] == -1.0).sum())
    pitch = math.atan2(0.6, 6.0)  # the camera looks down by this angle; the horizon is that far above centre
    horizon_row = res / 2 - math.tan(pitch) / math.tan(math.radians(20.0)) * res / 2
    assert abs(sky_rows - horizon_row) <= 1.0
    assert (img[sky_rows + 1:, :, 0] > 0).all()  # every pixel below the horizon is lit plane


def test_supersampling_averages_the_stratified_sub_pixels():
    cam = top_camera(1.0, (0.5, 0.5), 3.0)
    light = DirectionalLight((0, 0, 1), 1.0)
    one = render_preview(Probe(), cam, light, resolution=(4, 4), spp=1)
    four = render_preview(Probe(), cam, light, resolution=(4, 4), spp=4)
    # B = frac(u) is linear in u inside a pixel: the 2x2 stratified mean equals the centre value
    np.testing.assert_allclose(four[..., 2], one[..., 2], atol=1e-6)


@pytest.mark.parametrize("kwargs, match", [
    (dict(resolution=(0, 4)), "resolution"),
    (dict(spp=0), "spp"),
])
def test_bad_arguments_raise_clear_errors(kwargs, match):
    with pytest.raises(InputError, match=match):
        render_preview(Probe(), top_camera(), DirectionalLight(), **kwargs)


def test_bad_camera_and_light_raise_clear_errors():
    with pytest.raises(InputError, match="camera origin"):
        render_preview(Probe(), PinholeCamera(origin=(0, 0, -1), target=(0, 0, -2), up=(0, 1, 0)), DirectionalLight())
    with pytest.raises(InputError, match="camera fov"):
        render_preview(Probe(), PinholeCamera(fov=180.0), DirectionalLight())
    with pytest.raises(InputError, match="point light position"):
        render_preview(Probe(), top_camera(), PointLight(position=(0, 0, -1)))
