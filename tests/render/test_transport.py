"""Ground-truth environment-to-pixel transport (jprt.render.transport) against Mitsuba's renders."""

from __future__ import annotations

import numpy as np
import pytest

from jprt.methods.wavelet_prt import model as wp
from jprt.render.cameras import camera_rays, look_at
from jprt.render.images import indirect_rays
from jprt.render.lights import EnvMap
from jprt.render.scenes import SceneHandle, glossy_cornell
from jprt.render.transport import environment_transport
from jprt.sphere import envmap

N = 4  # cube-map face size


@pytest.fixture(scope="module")
def setup():
    cube = envmap.synthetic_environments(1, N, seed=2)[0]
    handle = SceneHandle(glossy_cornell(open_top=True, floor_roughness=0.2, sphere_roughness=0.1),
                         EnvMap.create(envmap.render_equirect(cube, scale=8)))
    cam = look_at((0.3, 1.2, 3.6), (0.0, -0.1, 0.0), width=6, height=6)
    o, d = camera_rays(cam)
    return handle, cube, o.reshape(-1, 3), d.reshape(-1, 3)


SPP, DEPTH = 512, 5


@pytest.fixture(scope="module")
def transport(setup):
    """``get(min_depth)``: the transport of ``setup``'s pixels at SPP samples and paths up to DEPTH
    bounces, traced once per module (the wavelet check below reuses the comparison's)."""
    handle, _, o, d = setup
    done = {}

    def get(min_depth):
        if min_depth not in done:
            done[min_depth] = environment_transport(handle, o, d, face_size=N, spp=SPP, seed=1, min_depth=min_depth,
                                                    max_depth=DEPTH)
        return done[min_depth]

    return get


def _rel(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.mark.parametrize("min_depth", [pytest.param(0, marks=pytest.mark.slow), 2])
def test_transport_relights_like_mitsuba(setup, transport, min_depth):
    """B = sum_t T_t L_t (all path lengths, or indirect only) agrees with Mitsuba's render of the same
    environment within the noise of two Mitsuba renders with different seeds."""
    handle, cube, o, d = setup
    spp, depth = SPP, DEPTH
    t = transport(min_depth)
    assert t.shape == (36, 6, N, N, 3) and np.all(t >= 0)
    b = np.einsum("ptijc,tijc->pc", t, cube)

    def mitsuba(seed):
        r = indirect_rays(handle, o, d, spp=spp, seed=seed, max_depth=depth)
        return r.full if min_depth == 0 else r.indirect

    ref, ref2 = mitsuba(5), mitsuba(6)
    noise = _rel(ref2, ref)
    assert _rel(b, ref) < 1.5 * noise + 0.02, (_rel(b, ref), noise)
    assert b.mean() == pytest.approx(ref.mean(), rel=0.1)


def test_transport_check_in_the_wavelet_basis(setup, transport):
    """Projected onto the Haar basis, all wavelets reproduce the texel-domain product exactly and the
    truncation error falls with K (on the indirect transport the comparison above traced)."""
    _, cube, _, _ = setup
    t = transport(2)
    out = wp.transport_check(t, cube, ks=(4, 16, 96))
    assert _rel(out["wavelet_all"], out["full"]) < 1e-4
    assert _rel(out["by_k"][96], out["full"]) < 1e-4
    assert _rel(out["by_k"][16], out["full"]) < _rel(out["by_k"][4], out["full"])


def test_transport_argument_checks(setup):
    handle, _, o, d = setup
    with pytest.raises(ValueError, match="min_depth"):
        environment_transport(handle, o, d, face_size=N, spp=4, min_depth=3, max_depth=3)
    with pytest.raises(ValueError, match="spp"):
        environment_transport(handle, o, d, face_size=N, spp=0)
