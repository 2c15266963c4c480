"""Training scenes of the learned observation: the body in database poses, rendered by the
project's own JAX ray caster (:mod:`jaxmocap.render`) under randomised light.

Two passes, so that every training step sees new light on the same geometry:

1. **Geometry** (:func:`render_geometry`, once per data set, cached): a pose drawn like the pose
   database's (:func:`jaxmocap.posedb.sample_poses` over the training clips: blends, mirrors,
   jitter, every orientation), a webcam placed at random around it (1.6-4 m, above or below the
   chest, 45-70 deg field of view), the crop a tracker would take around the shirt (its side
   1.1-2.4x the shirt's bounding box, centre jittered), and per crop pixel: albedo, normal, 3D
   point, class (:mod:`jaxmocap.observe.classes`) and, for up to :data:`MAX_LAMPS` lamp
   positions, whether the lamp sees the point (a shadow ray cast back from the lamp).
2. **Light** (:func:`shade`, every step, inside the jitted training step), drawn from a key as
   data, not code paths (``../shared/STYLE.md``): 1-3 lamps, each a point light with its own
   black-body colour (2000-10000 K, :func:`blackbody_rgb`) and a green-magenta tint, inverse-
   square fall-off and hard shadows, dimmed or off at random; a coloured ambient (bounced
   light); Blinn-Phong highlights; haze (desaturation towards grey); the camera's white-balance
   gains, exposure, tone curve (gamma and an S-curve), Gaussian blur, sensor noise, JPEG's
   4:2:0 chroma subsampling (not its DCT quantisation) and 8-bit quantisation. The background
   is random clutter drawn in the same light: a textured wall and rectangles / discs whose
   colours are often exactly the garment's or skin's albedo (so "shirt-coloured" alone never
   means shirt), and now and then an occluder in front of the body (its pixels background).

MuJoCo and Cycles renders are never training data (the test world measures the transfer from
this renderer to those); nothing here reads a test split.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jaxmocap.body import BodyModel
from jaxmocap.camera import camera_center, look_at, pixel_rays, project, to_camera
from jaxmocap.garment import Garment, albedo
from jaxmocap.render import cast_rays, posed_scene, render_rays, shirt_points
from jaxmocap.sampling import crop_uv

from .classes import Classes, labels_of

MAX_LAMPS = 3
IMAGE_SIZE = (640, 480)  # a webcam (Wang et al. §3); only the crop is rendered
# crop side / the shirt's bounding box, by what the model is for: "crop" the shirt tracker's
# crop (2.6 x its search scale); "frame" a stereo rig's whole frame read at the model's scale
# (jaxmocap.trackers.stereo_pf.learned: a person ~2 m from a 320 x 240 camera at half
# resolution spans 1.1-3.5 x the shirt's box, more of the room than a crop holds). Tried for
# "frame" and measured no better (docs/results/learned_pf.md): 60% of the crops centred on a
# hand, and crops at the full resolution's scale (0.5-1.6 x the box).
FRAMINGS = {"crop": (1.1, 2.4), "frame": (1.1, 3.5)}
CROP_SCALE = FRAMINGS["crop"]
CROP_SHIFT = 0.15  # crop centre jitter, fraction of its side
CAMERA_DISTANCE = (1.6, 4.0)  # m, horizontal
CAMERA_RISE = (-0.5, 0.9)  # m, camera height above the shirt's centre
FOV = (45.0, 70.0)  # deg, horizontal
LAMP_DISTANCE = (0.8, 4.0)  # m from the shirt's centre
LAMP_ELEVATION = (-10.0, 75.0)  # deg
KELVIN = (2000.0, 10000.0)  # lamp colour temperatures (issue 49)
N_SHAPES = 10  # clutter shapes per background


class Geometry(NamedTuple):
    """Pass 1, stacked over samples: per crop pixel albedo (linear RGB), world normal and
    point, class id, body mask, and each lamp's visibility; lamp positions and camera centres."""

    albedo: Float[Array, "m n n 3"]
    normal: Float[Array, "m n n 3"]
    point: Float[Array, "m n n 3"]
    label: Array  # (m, n, n) int32
    body: Array  # (m, n, n) bool
    lit: Array  # (m, L, n, n) bool
    lamps: Float[Array, "m L 3"]
    eye: Float[Array, "m 3"]
    centre: Float[Array, "m 3"]


def _uniform(key, lo_hi, shape=(), dtype=jnp.float32):
    return jax.random.uniform(key, shape, dtype, minval=lo_hi[0], maxval=lo_hi[1])


def _geometry_one(model: BodyModel, garment: Garment, classes: Classes, n: int, q, key,
                  crop_scale: tuple[float, float] = CROP_SCALE):
    dt = q.dtype
    ks = jax.random.split(key, 10)
    pts, valid = shirt_points(model, garment, q)
    centre = jnp.sum(jnp.where(valid[:, None], pts, 0), 0) / jnp.maximum(jnp.sum(valid), 1)
    az = jax.random.uniform(ks[0], (), dt, 0, 2 * jnp.pi)
    dist = _uniform(ks[1], CAMERA_DISTANCE, (), dt)
    rise = _uniform(ks[2], CAMERA_RISE, (), dt)
    eye = centre + jnp.stack([dist * jnp.cos(az), dist * jnp.sin(az), rise]).astype(dt)
    target = centre + 0.1 * jax.random.normal(ks[3], (3,), dt)
    w, h = IMAGE_SIZE
    fov = jnp.deg2rad(_uniform(ks[4], FOV, (), dt))
    fx = (w / 2) / jnp.tan(fov / 2)
    zero, one = jnp.zeros((), dt), jnp.ones((), dt)
    K = jnp.stack([jnp.stack([fx, zero, one * (w - 1) / 2]),
                   jnp.stack([zero, fx, one * (h - 1) / 2]),
                   jnp.stack([zero, zero, one])])
    cam = look_at(eye, target, width=w, height=h, K=K)
    front = valid & (to_camera(cam, pts)[:, 2] > 0)
    uv = project(cam, pts)
    big = jnp.asarray(1e6, dt)
    lo = jnp.min(jnp.where(front[:, None], uv, big), 0)
    hi = jnp.max(jnp.where(front[:, None], uv, -big), 0)
    side = jnp.max(hi - lo) * _uniform(ks[5], crop_scale, (), dt)
    mid = (lo + hi) / 2 + CROP_SHIFT * side * jax.random.uniform(ks[6], (2,), dt, -1, 1)
    window = jnp.concatenate([mid - side / 2, jnp.stack([side, side])])
    o = camera_center(cam)
    dirs = pixel_rays(cam, crop_uv(window, n))[1]
    hits = render_rays(model, garment, q, o, dirs, cam.R[2])
    rho = albedo(garment, hits.geom, hits.patch)
    label = labels_of(classes, hits.geom, hits.colour)
    # lamps around the shirt's centre; a lamp sees a point when the ray cast from the lamp
    # towards it first hits that point (1 mm tolerance)
    la = jax.random.uniform(ks[7], (MAX_LAMPS,), dt, 0, 2 * jnp.pi)
    le = jnp.deg2rad(_uniform(ks[8], LAMP_ELEVATION, (MAX_LAMPS,), dt))
    ld = _uniform(ks[9], LAMP_DISTANCE, (MAX_LAMPS,), dt)
    lamps = centre[None] + ld[:, None] * jnp.stack(
        [jnp.cos(le) * jnp.cos(la), jnp.cos(le) * jnp.sin(la), jnp.sin(le)], -1)
    scene = posed_scene(model, q)
    p = hits.point.reshape(-1, 3)

    def sees(lamp):
        v = p - lamp[None]
        d = jnp.linalg.norm(v, axis=-1)
        sh = cast_rays(scene, garment, lamp, v / jnp.maximum(d, 1e-9)[:, None])
        return (sh.t >= d - 1e-3).reshape(n, n)

    lit = jax.vmap(sees)(lamps) & ~hits.background[None]
    return Geometry(rho, hits.normal, jnp.where(hits.background[..., None], 0, hits.point),
                    label, ~hits.background, lit, lamps, o, centre)


def render_geometry(model: BodyModel, garment: Garment, classes: Classes,
                    poses: Float[np.ndarray, "m n_dof"], key: PRNGKeyArray, n: int,
                    batch: int = 8, progress=None, framing: str = "crop") -> Geometry:
    """Pass 1 (module docstring) for every pose, ``batch`` at a time under one ``vmap``; float16
    albedo / normal / point (they only feed the light of pass 2). ``progress(k)`` is called after
    each batch with the number of samples done. ``framing``: a key of :data:`FRAMINGS`."""
    spec = FRAMINGS[framing]
    fn = jax.jit(jax.vmap(lambda q, k: _geometry_one(model, garment, classes, n, q, k, spec)))
    keys = jax.random.split(key, len(poses))
    out = []
    m = len(poses)
    for i in range(0, m, batch):
        j = min(i + batch, m)
        qs, kk = np.asarray(poses[i:j], np.float32), keys[i:j]
        pad = batch - (j - i)
        if pad:
            qs = np.concatenate([qs, np.repeat(qs[-1:], pad, 0)])
            kk = jnp.concatenate([kk, jnp.repeat(kk[-1:], pad, 0)])
        g = jax.device_get(fn(jnp.asarray(qs), kk))
        out.append(jax.tree.map(lambda a, k=j - i: a[:k], g))
        if progress is not None:
            progress(j - i)
    g = jax.tree.map(lambda *a: np.concatenate(a), *out)
    half = dict(albedo=g.albedo.astype(np.float16), normal=g.normal.astype(np.float16),
                point=g.point.astype(np.float16))
    return g._replace(**half, label=g.label.astype(np.int8))


# ----------------------------------------------------------------------------- light (pass 2)

_WAVELENGTHS = np.array([610e-9, 545e-9, 465e-9])  # m: the camera's R, G, B peaks


def blackbody_rgb(kelvin: Float[Array, "*s"]) -> Float[Array, "*s 3"]:
    """Relative RGB of a black body at ``kelvin``: Planck's law at the R, G, B peaks of a
    camera (610, 545, 465 nm), normalised to mean 1. 2700 K is orange (R/B ~ 3), 6500 K near
    neutral, 10000 K blue."""
    h, c, kb = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lam = jnp.asarray(_WAVELENGTHS, jnp.float32)
    x = (h * c / kb) / (lam.reshape((1,) * kelvin.ndim + (3,)) * kelvin[..., None])
    rad = 1.0 / (lam.reshape((1,) * kelvin.ndim + (3,)) ** 5 * jnp.expm1(x))
    return rad / jnp.mean(rad, -1, keepdims=True)


def _light_colour(key, shape=()):
    k1, k2 = jax.random.split(key)
    kelvin = jnp.exp(_uniform(k1, (np.log(KELVIN[0]), np.log(KELVIN[1])), shape))
    tint = 0.12 * jax.random.normal(k2, shape)  # green-magenta
    rgb = blackbody_rgb(kelvin) * jnp.stack([1 + tint / 2, 1 - tint, 1 + tint / 2], -1)
    return rgb / jnp.mean(rgb, -1, keepdims=True)


def _background(key, n: int, palette: Float[Array, "k 3"], light: Float[Array, " 3"]):
    """Random clutter (linear RGB, n x n): a textured wall and :data:`N_SHAPES` shapes; a shape
    takes one of ``palette``'s albedos (the garment's colours and skin) half of the time."""
    ks = jax.random.split(key, 8)
    yy, xx = jnp.meshgrid(jnp.linspace(0, 1, n), jnp.linspace(0, 1, n), indexing="ij")
    base = jax.random.uniform(ks[0], (3,), minval=0.05, maxval=0.8)
    f = jax.random.normal(ks[1], (3, 2)) * 6
    ph = jax.random.uniform(ks[2], (3,), maxval=6.3)
    tex = sum(jnp.sin(f[i, 0] * xx + f[i, 1] * yy + ph[i]) for i in range(3)) / 3
    img = base[None, None] * (1 + 0.25 * tex)[..., None]
    kk = jax.random.split(ks[3], N_SHAPES)

    def shape(img, k):
        a = jax.random.split(k, 7)
        c = jax.random.uniform(a[0], (2,))
        r = jnp.exp(jax.random.uniform(a[1], (2,), minval=np.log(0.04), maxval=np.log(0.45)))
        rect = (jnp.abs(xx - c[0]) < r[0]) & (jnp.abs(yy - c[1]) < r[1])
        disc = ((xx - c[0]) / r[0]) ** 2 + ((yy - c[1]) / r[1]) ** 2 < 1
        mask = jnp.where(jax.random.bernoulli(a[2]), rect, disc)
        pick = palette[jax.random.randint(a[3], (), 0, palette.shape[0])]
        rand = jax.random.uniform(a[4], (3,), minval=0.02, maxval=0.95)
        col = jnp.where(jax.random.bernoulli(a[5], 0.5), pick, rand)
        col = col * jax.random.uniform(a[6], (), minval=0.4, maxval=1.3)
        return jnp.where(mask[..., None], col[None, None], img), None

    img, _ = jax.lax.scan(shape, img, kk)
    return img * light[None, None]


def _blur(img: Float[Array, "n n 3"], sigma) -> Float[Array, "n n 3"]:
    t = jnp.arange(-3, 4, dtype=img.dtype)
    k = jnp.exp(-0.5 * (t / jnp.maximum(sigma, 1e-3)) ** 2)
    k = k / jnp.sum(k)
    pad = jnp.pad(img, ((3, 3), (3, 3), (0, 0)), mode="edge")
    n = img.shape[0]
    rows = sum(k[i] * pad[i:i + n] for i in range(7))
    return sum(k[i] * rows[:, i:i + n] for i in range(7))


def _chroma_subsample(v: Float[Array, "n n 3"]) -> Float[Array, "n n 3"]:
    """JPEG's 4:2:0: Cb and Cr averaged over 2x2 blocks (BT.601), luma kept."""
    m = jnp.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])
    ycc = v @ m.T
    n = v.shape[0]
    c = ycc[..., 1:].reshape(n // 2, 2, n // 2, 2, 2).mean((1, 3))
    c = jnp.repeat(jnp.repeat(c, 2, 0), 2, 1)
    return jnp.concatenate([ycc[..., :1], c], -1) @ jnp.linalg.inv(m).T


def shade(key: PRNGKeyArray, g: Geometry, palette: Float[Array, "k 3"]
          ) -> tuple[Float[Array, "n n 3"], Int[Array, "n n"]]:
    """Pass 2 for one sample of :class:`Geometry` (unbatched): ``(image, labels)``, an 8-bit
    camera image (float, 0..255) of the crop under light drawn from ``key`` (module docstring)
    and its classes (the render's, background where an occluder was drawn). ``palette``:
    albedos the clutter copies (the garment's colours and skin)."""
    ks = jax.random.split(key, 20)
    L = g.lamps.shape[0]
    n = g.label.shape[-1]
    rho, nrm, x = (a.astype(jnp.float32) for a in (g.albedo, g.normal, g.point))
    on = jnp.arange(L) < jax.random.randint(ks[0], (), 1, L + 1)
    level = jnp.exp(_uniform(ks[1], (np.log(0.4), np.log(2.5)), (L,)))
    dimmed = jax.random.bernoulli(ks[2], 0.15, (L,)) & (jnp.arange(L) > 0)
    level = level * jnp.where(dimmed, _uniform(ks[3], (0.0, 0.25), (L,)), 1.0) * on
    colour = _light_colour(ks[4], (L,))
    d0 = jnp.linalg.norm(g.lamps - g.centre[None], axis=-1)  # level is the light at the shirt
    to_l = g.lamps[:, None, None, :] - x[None]
    d = jnp.maximum(jnp.linalg.norm(to_l, axis=-1), 1e-3)
    ldir = to_l / d[..., None]
    fall = (d0[:, None, None] / d) ** 2
    cos = jnp.maximum(jnp.sum(ldir * nrm[None], -1), 0) * g.lit * fall
    view = g.eye[None, None] - x
    view = view / jnp.maximum(jnp.linalg.norm(view, axis=-1, keepdims=True), 1e-6)
    half = ldir + view[None]
    half = half / jnp.maximum(jnp.linalg.norm(half, axis=-1, keepdims=True), 1e-6)
    shin = jnp.exp(_uniform(ks[5], (np.log(4.0), np.log(60.0))))
    ks_ = _uniform(ks[6], (0.0, 0.35))
    spec = ks_ * jnp.maximum(jnp.sum(half * nrm[None], -1), 0) ** shin * g.lit * fall
    amb_level = jnp.exp(_uniform(ks[7], (np.log(0.03), np.log(0.6))))
    ambient = amb_level * _light_colour(ks[8])
    direct = jnp.einsum("lhw,l,lc->hwc", cos, level, colour)
    lin = rho * (ambient[None, None] + direct) + jnp.einsum("lhw,l,lc->hwc", spec, level, colour)
    room_light = ambient + jnp.sum(level[:, None] * colour, 0) * _uniform(ks[9], (0.2, 0.9))
    bg = _background(ks[10], n, palette, room_light)
    lin = jnp.where(g.body[..., None], lin, bg)
    # an occluder in front of the body now and then: its pixels are background
    occ = _background(ks[11], n, palette, room_light)
    yy, xx = jnp.meshgrid(jnp.linspace(0, 1, n), jnp.linspace(0, 1, n), indexing="ij")
    edge = jax.random.uniform(ks[12], (), minval=0.0, maxval=1.0)
    side = jax.random.bernoulli(ks[13])
    occ_mask = jnp.where(side, xx < edge * 0.4, xx > 1 - edge * 0.4)
    occ_mask = occ_mask & jax.random.bernoulli(ks[14], 0.2)
    lin = jnp.where(occ_mask[..., None], occ, lin)
    label = jnp.where(occ_mask, 0, g.label.astype(jnp.int32))
    # haze / bounced light: towards grey
    lum = jnp.sum(lin * jnp.array([[[0.299, 0.587, 0.114]]]), -1, keepdims=True)
    lin = lin + _uniform(ks[15], (0.0, 0.45)) * (lum - lin)
    # camera: white-balance gains, exposure, blur, tone curve, noise, chroma subsampling
    gains = jnp.exp(0.15 * jax.random.normal(ks[16], (3,)))
    expo = jnp.exp(_uniform(ks[17], (np.log(0.5), np.log(2.0))))
    lin = _blur(lin * gains[None, None] * expo, _uniform(ks[18], (0.0, 1.3)))
    k = jax.random.split(ks[19], 5)
    gamma = _uniform(k[0], (1.6, 2.6))
    v = jnp.clip(lin, 0, 1) ** (1 / gamma)
    v = v + _uniform(k[1], (0.0, 0.6)) * (v * v * (3 - 2 * v) - v)  # S-curve
    v = v + _uniform(k[2], (0.0, 0.03)) * jax.random.normal(k[3], v.shape)
    v = jnp.where(jax.random.bernoulli(k[4]), _chroma_subsample(v), v)
    return jnp.round(jnp.clip(v, 0, 1) * 255), label


def palette_of(garment: Garment) -> Float[Array, "k 3"]:
    """The albedos clutter copies: the garment's colours and its skin."""
    return jnp.concatenate([garment.colours, garment.skin_rgb[None]]).astype(jnp.float32)
