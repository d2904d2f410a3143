"""The Mitsuba plugins: registration, the ``lgsurface`` shape and its surface
interaction, and the error messages of bad input.

Oracles: Mitsuba's native ``sphere`` (its SurfaceInteraction: t, p, n, uv,
dp_du, dp_dv, sh_frame) for the same sphere given as an expression; the
closed-form chord of a sphere in float64 for rays spawned from a hit; finite
differences of the documented uv map (in float64, with the analytic radial
projection onto an ellipsoid) for dp_du / dp_dv.
"""
import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import VARIANT

SPHERE = {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - 1",
          "bbox_min": [-1.1, -1.1, -1.1], "bbox_max": [1.1, 1.1, 1.1]}


@pytest.fixture(autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()


def load_shape(**props):
    return mi.load_dict({"type": "scene", "s": {"type": "lgsurface", **props}})


def rays(o, d):
    o, d = (np.ascontiguousarray(np.asarray(v, np.float32).T) for v in (o, d))
    return mi.Ray3f(mi.Point3f(o), mi.Vector3f(d))


def random_rays(rng, n, centre, spread=0.9, dist=5.0):
    """Rays from a sphere of radius ``dist`` around ``centre`` towards random
    points within ``spread`` of it."""
    o = rng.normal(size=(n, 3))
    o = centre + dist * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = centre + rng.uniform(-spread, spread, (n, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def np3(v):
    """A Dr.Jit array as numpy: (n, 3) for vectors, (n,) for scalars."""
    a = np.array(v)
    a = a.astype(np.float64) if a.dtype.kind == "f" else a
    return a.T if dr.depth_v(v) > 1 else a


# ---- float32 error model of test05 (see its docstring) ----------------------

U32 = 2.0 ** -24                     # float32 unit roundoff


def gamma(k):
    """Higham's bound of k float32 roundings: k u / (1 - k u)."""
    return k * U32 / (1 - k * U32)


E_RSQRT = 8 * U32                    # Dr.Jit rsqrt (and rcp): relative
E_ATAN2, E_ACOS, E_ASIN = 2.0 ** -20, 2.0 ** -21, 2.0 ** -22   # absolute (radians)


def _norm(v):
    return np.linalg.norm(v, axis=-1)


def sphere_ray_bounds(o, d, c, R, Winv, diag):
    """Per ray (float32 o, d as float64 arrays): b (distance of the line from
    the centre c), h (half chord), the two sides' displacement roundings and
    the band around tangency where float32 decides hit or miss."""
    dn = d / _norm(d)[:, None]
    tau = ((c - o) * dn).sum(1)
    b = _norm(c - o - tau[:, None] * dn)
    h = np.sqrt(np.maximum(R * R - b * b, 0))
    plane = o + tau[:, None] * dn - c                     # Mitsuba's o'
    disp_native = _norm(2 * U32 * (np.abs(o) + np.abs(tau[:, None] * d))
                        + U32 * np.abs(plane) + 2 * U32 * np.abs(c))
    A = np.abs(Winv)
    disp_o = _norm(gamma(5) * (np.abs(o) @ A[:3, :3].T + A[:3, 3]))
    disp_d = _norm(gamma(4) * (np.abs(d) @ A[:3, :3].T))
    dR, dC = gamma(8) * R, gamma(4) * (b * b + R * R)
    graze = disp_native + disp_o + (np.abs(tau) + R) * disp_d + dR + dC / (2 * R) \
        + (0.5e-6 * diag) ** 2 / (2 * R)
    return dict(b=b, h=h, disp_native=disp_native, disp_o=disp_o, disp_d=disp_d, dR=dR, dC=dC,
                undecided=np.abs(R - b) <= graze)


def native_sphere_tolerances(a, b, o, d, c, R, Rot, Winv, diag):
    """Per-ray bounds of |native - lgsurface| for each field of the
    interaction (dicts of numpy arrays, native ``a`` and lgsurface ``b``
    hits only); derived in test05's docstring."""
    ray = sphere_ray_bounds(o, d, c, R, Winv, diag)
    h, bb = ray["h"], ray["b"]
    tol = {}
    with np.errstate(divide="ignore", invalid="ignore"):
        lever = 1 + bb / h
        e_native = (ray["disp_native"] * lever + (ray["dC"] + 2 * R * ray["dR"]) / (2 * h)
                    + gamma(3) * bb + gamma(6) * h + U32 * np.abs(a["t"]))
        e_lg = ((ray["disp_o"] + np.abs(b["t"]) * ray["disp_d"]) * lever + 1e-6 * diag
                + gamma(5) * np.abs(b["t"]))
        tol["t"] = e_native + e_lg
        dt = np.abs(a["t"] - b["t"])
        tol["p"] = dt[:, None] * np.abs(d) \
            + 4 * U32 * (np.abs(o) + np.abs(a["t"])[:, None] * np.abs(d)) \
            + 4 * U32 * (np.abs(o) + np.abs(b["t"])[:, None] * np.abs(d))

        # ---- the hit in object space, and each side's rounding of it
        A = np.abs(Winv)
        q = (b["p"] - c) @ Rot
        dq_lg = _norm(gamma(5) * (np.abs(b["p"]) @ A[:3, :3].T + A[:3, 3]))
        dq_native = np.sqrt(3) * gamma(20) * (np.abs(a["p"]).sum(1) + np.abs(c).sum())
        dp = _norm(a["p"] - b["p"])
        Dq = dp + dq_native + dq_lg
        r, rho, z = _norm(q), np.hypot(q[:, 0], q[:, 1]), np.abs(q[:, 2])
        zeta = z / r
        rho_min = np.maximum(rho - Dq, 0)

        # ---- n: the direction of p - c
        tol["n"] = (2 * dp / (r - dp)
                    + 2 * np.sqrt(3) * U32 * (_norm(a["p"]) + _norm(c)) / R + gamma(4) + E_RSQRT
                    + 2 * dq_lg / R + gamma(2) + gamma(4) + gamma(4) + E_RSQRT)
        # ---- uv
        tu = Dq / (2 * np.pi * rho_min) + 2 * (E_ATAN2 / (2 * np.pi) + 2 * U32)
        tu = np.where(rho_min > 0, tu, 0.5)
        off_unit = np.abs(_norm((a["p"] - c) @ Rot) / R - 1) + (dq_native + ray["dR"]) / R
        ev_native = (off_unit + 16 * np.sqrt(2) * U32 + 2 * E_ASIN + 2 * U32) / np.pi + 2 * U32
        dz = 2.5 * U32 + E_RSQRT
        z_max = zeta + dq_lg / r + dz
        slope = np.where(z_max < 1, dz / np.sqrt(np.maximum(1 - z_max ** 2, 1e-300)), np.inf)
        ev_lg = (np.minimum(slope, np.arccos(1 - dz)) + E_ACOS) / np.pi + 2 * U32
        tol["uv"] = np.stack([tu, Dq / (np.pi * (r - Dq)) + ev_native + ev_lg], 1)
        # ---- tangents
        tol["dp_du"] = (2 * np.pi * Dq
                        + 2 * np.pi * np.sqrt(3) * gamma(6) * (np.abs(q[:, 0]) + np.abs(q[:, 1]))
                        + gamma(80) * 2 * np.pi * rho)
        lip = np.where(rho_min > 0, np.pi * (2 + (z + Dq) / rho_min), np.inf)
        tol["dp_dv"] = (lip * Dq + np.pi * np.sqrt(3) * gamma(18) * (z + rho)
                        + gamma(80) * np.pi * r)
        # ---- shading frame and wi, from their inputs' differences
        ddu, dn = _norm(a["dp_du"] - b["dp_du"]), _norm(a["n"] - b["n"])
        L = np.minimum(_norm(a["dp_du"]), _norm(b["dp_du"]))
        perp = ddu + 2 * L * dn
        tol["s"] = np.where(L > perp, 2 * perp / (L - perp), 2.0) \
            + 2 * (2 * gamma(5) + gamma(4) + E_RSQRT)
        ds = _norm(a["s"] - b["s"])
        tol["t_axis"] = (1 + 16 * U32) * (dn + ds) + 2 * np.sqrt(3) * gamma(2)
        dt_axis = _norm(a["t_axis"] - b["t_axis"])
        tol["wi"] = np.stack([ds, dt_axis, dn], 1) + 2 * gamma(3) + gamma(4) + E_RSQRT
    return tol, ray


# ---------------------------------------------------------------------------
#  Registration
# ---------------------------------------------------------------------------

def test01_register_idempotent():
    # Oracle: calling twice changes nothing and the plugins load by id.
    lgshape.register_plugins()
    lgshape.register_plugins()
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "lg_path"}, "s": SPHERE})
    assert type(scene.integrator()).__name__ == "LGPathIntegrator"
    assert type(scene.shapes()[0]).__name__ == "LGSurface"


@pytest.mark.parametrize("name", ["scalar_rgb", "scalar_spectral"])
def test02_scalar_variant_error(name):
    mi.set_variant(name)
    with pytest.raises(RuntimeError, match=f"'{name}' is a scalar variant"):
        lgshape.register_plugins()


@pytest.mark.parametrize("name", ["llvm_ad_mono", "llvm_ad_spectral"])
def test03_other_variants_render(name):
    # Oracle: the same tiny scene renders in rgb and in `name` with the same
    # mean brightness (within Monte Carlo error of 16 spp) and no NaN.
    def render():
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "lg_path", "max_depth": 3},
            "sensor": {"type": "perspective", "fov": 45,
                       "to_world": mi.ScalarTransform4f().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 16, "height": 16},
                       "sampler": {"type": "independent", "sample_count": 16}},
            "env": {"type": "constant"}, "s": SPHERE})
        return np.array(mi.render(scene))
    rgb = render()
    mi.set_variant(name)
    lgshape.register_plugins()
    other = render()
    assert np.all(np.isfinite(other))
    assert abs(other.mean() - rgb.mean()) < 0.05 * rgb.mean()


# ---------------------------------------------------------------------------
#  The shape
# ---------------------------------------------------------------------------

def test04_bbox_and_placeholder():
    # Oracle: the world box of a transformed library torus, by hand; the
    # placeholder triangle makes it the scene's bounds and is never hit.
    T = mi.ScalarTransform4f().translate([1, 2, 3]) @ mi.ScalarTransform4f().scale([2, 1, 1])
    scene = load_shape(surface="torus", R=1.0, r=0.5, to_world=T)
    h = 1.1 * 1.5
    box = scene.bbox()
    assert np.allclose(box.min, [1 - 2 * h, 2 - h, 3 - 0.6], atol=1e-5)
    assert np.allclose(box.max, [1 + 2 * h, 2 + h, 3 + 0.6], atol=1e-5)
    shape = scene.shapes()[0]
    assert np.allclose(shape.bbox().min, box.min) and np.allclose(shape.bbox().max, box.max)
    o, d = random_rays(np.random.default_rng(1), 20000, np.array([1., 2, 3]), spread=3)
    assert not np.any(np3(scene.ray_intersect(rays(o, d)).is_valid()))
    text = str(shape)
    assert "torus(R=1, r=0.5)" in text and "SmoothDiffuse" in text


def test05_interaction_matches_native_sphere():
    """Mitsuba's sphere (radius R = 1.3, rotated and moved) and the same
    sphere as an lgsurface agree on every field of the interaction, within
    per-ray bounds of the two sides' float32 errors
    (:func:`native_sphere_tolerances`). Oracle: Mitsuba's native ``sphere``.

    Notation: u = 2^-24, gamma_k = k u / (1 - k u) (k roundings); per ray, b
    is the distance of its line from the centre c, h = sqrt(R^2 - b^2) the
    half chord, tau the ray's parameter nearest c; q = the lgsurface hit in
    its object space (the to_world here is a rotation and a translation, so
    object distances are world distances), rho = |q_xy|, r = |q|, zeta =
    |q_z| / r. Dr.Jit's float32 functions: rsqrt and rcp are an estimate
    refined by one Newton step on LLVM; AVX2's vrsqrtps is within 1.5 2^-12,
    so the refined value is within 1.5 (1.5 2^-12)^2 + 3u < 8u (measured on
    an AMD EPYC, AVX2 only: 3.25u; AVX-512's vrsqrt14ps, 2^-14, leaves about
    1u, the likely reason why the old fixed 1e-5 on uv held elsewhere and
    failed on the EPYC, off by 2.09e-5 near a pole). atan2 is within 2^-20 (its header's
    5.96e-7 for atan, the quadrant's +-pi, ulp(pi) / 2, and the division:
    8.05e-7), acos within 2^-21 (2 ulp of pi; its header says 2.38e-7,
    measured 2.98e-7), asin 2^-22 (its header: 1.19e-7).

    - Hit or miss: the same, except within the band |R - b| <= the sum of
      both sides' displacement errors below (float32 decides tangent rays).
    - t: moving the ray by delta moves the root by <= delta (1 + b / h), an
      error dC in Mitsuba's C = |o'|^2 - R^2 moves it by dC / (2 h), one dR
      in its float32 radius by R dR / h. Mitsuba (float32 quadratic about
      the plane point o' = o + tau d - c): delta = 2u (|o| + |tau d|) +
      u |o'| + 2u |c| per component, dC = gamma_4 (b^2 + R^2), dR = gamma_8 R
      (1.3 in float32, the rotation's column norm), plus gamma_3 b (B),
      gamma_6 h (A and the solve) and u t (adding tau). lgsurface: the ray
      moved to object space in float32, delta = gamma_5 (|W^-1| |o| +
      |W^-1 t|) + t gamma_4 |W^-1| |d|, plus the search's documented
      accuracy, 1e-6 of the box diagonal, and the float32 t, gamma_5 t.
    - p = o + t d on both sides: |t_a - t_b| |d| + 2 (2u (|o| + t |d|)).
    - The other fields are functions of the hit point: their difference is
      the function's Lipschitz bound times Dq = |p_a - p_b| + the two
      sides' rounding of q (Mitsuba's float32 inverse of to_world and the
      affine product: gamma_20 (|p|_1 + |c|_1) per component; lgsurface's
      float32 W^-1 p: gamma_5 (|W^-1| |p| + |W^-1 t|)), plus each side's
      evaluation error:
      - n, the direction of p - c: 2 |p_a - p_b| / r, plus Mitsuba's p - c
        (2u (|p| + |c|) / R) and normalize (gamma_4 + rsqrt), lgsurface's
        q (2 dq / R), gradient 2q (gamma_2), N g (gamma_4) and normalize.
      - u = atan2(q_y, q_x) / 2 pi: d u = |d q_xy| / (2 pi rho), so
        Dq / (2 pi (rho - Dq)), plus on each side 2^-20 / 2 pi and 2u (the
        +2 pi and the product); compared modulo 1 (hits on either side of
        the seam); unbounded within Dq of the axis.
      - v: lgsurface takes acos(zeta^) / pi of zeta^ = z rsqrt(r^2), whose
        error is dz = 2.5u + 8u (r^2, its rsqrt, the product); with
        d acos(zeta) / d zeta = 1 / sqrt(1 - zeta^2), that is
        dz / sqrt(1 - zeta_max^2), zeta_max = zeta + dq / r + dz (and at
        most acos(1 - dz), where that slope is infinite), plus 2^-21.
        Mitsuba's unit_angle_z, 2 asin(|v -+ e_z| / 2), is well conditioned
        (16 sqrt(2) u for the norm, 2 asin errors) but assumes |v| = 1: its
        local point is off the unit sphere by | |q_a| / R - 1 | + (dq + dR)
        / R, which moves theta by at most that (tan(theta / 2) <= 1 on its
        hemisphere). Plus the geometric Dq / (pi (r - Dq)); 2u per side for
        the product by 1 / pi.
      - dp_du = 2 pi Rot (-q_y, q_x, 0) on both sides: 2 pi Dq, Mitsuba's
        gamma_6 (to_world, the 2 pi) and lgsurface's gamma_80 |dp_du| (its
        solve [grad u; grad v; grad f] X = I: grad u 5, grad v 10, the cross
        product 16 sqrt(3), det 24 and rcp 8, the product 1 and W 12
        roundings relative to |dp_du|: 73).
      - dp_dv = pi Rot (z x / rho, z y / rho, -rho): its Lipschitz bound
        pi (2 + (z + Dq) / rho_min) times Dq, Mitsuba's gamma_18 (cos phi =
        x rcp(rho): 11, z cos phi, to_world and pi), lgsurface's gamma_80.
      - sh_frame: on both sides s = normalize(dp_du - n (n . dp_du)) and
        t = n x s, and sh_frame.n is n (bit for bit). From its inputs'
        differences: s within 2 (|d dp_du| + 2 |dp_du| |d n|) / |dp_du| plus
        2 (2 gamma_5 + gamma_4 + rsqrt); t within |d n| + |d s| plus 2 sqrt(3)
        gamma_2; wi = (-d . s, -d . t, -d . n) within the axis' difference
        plus 2 gamma_3 and lgsurface's normalize(d).
    The bounds are a few times the differences seen (largest ratio about
    0.85, for t = n x s); they are tighter than the old fixed 1e-5 (1e-4 for
    the tangents) where the fields are well conditioned and wider only
    where they are not (uv and dp_dv near the poles, t near tangency).
    """
    from lgshape.plugins import common
    T = mi.ScalarTransform4f().translate([0.3, -0.2, 0.1]) @ \
        mi.ScalarTransform4f().rotate([0.6, 0.8, 0], 40)
    native = mi.load_dict({"type": "scene", "s": {
        "type": "sphere", "to_world": T @ mi.ScalarTransform4f().scale(1.3)}})
    lg = load_shape(expr="x^2 + y^2 + z^2 - 1.69", bbox_min=[-1.4] * 3, bbox_max=[1.4] * 3,
                    to_world=T)
    ray = rays(*random_rays(np.random.default_rng(2), 4000, np.array([0.3, -0.2, 0.1])))
    a, b = native.ray_intersect(ray), common.ray_intersect(lg, ray)
    o, d = np3(ray.o), np3(ray.d)
    W = np.array(T.matrix, np.float64)
    Winv = np.linalg.inv(W)
    c, R, diag = W[:3, 3], 1.3, np.linalg.norm([2.8] * 3)

    hit_a, hit_b = np3(a.is_valid()), np3(b.is_valid())
    undecided = sphere_ray_bounds(o, d, c, R, Winv, diag)["undecided"]
    assert not np.any((hit_a != hit_b) & ~undecided), "hit or miss differs away from tangency"
    hit = hit_a & hit_b
    assert hit.mean() > 0.5

    def fields(si):
        out = {f: np3(getattr(si, f))[hit] for f in ("t", "p", "n", "uv", "dp_du", "dp_dv", "wi")}
        out["s"], out["t_axis"] = np3(si.sh_frame.s)[hit], np3(si.sh_frame.t)[hit]
        assert np.array_equal(np3(si.sh_frame.n)[hit], out["n"])
        return out

    fa, fb = fields(a), fields(b)
    tol, _ = native_sphere_tolerances(fa, fb, o[hit], d[hit], c, R, W[:3, :3], Winv, diag)
    for field, bound in tol.items():
        diff = np.abs(fa[field] - fb[field])
        if field == "uv":
            diff[:, 0] = np.minimum(diff[:, 0], 1 - diff[:, 0])     # u is periodic
        bound = bound if bound.ndim == diff.ndim else bound[:, None]
        ratio = diff / bound
        worst = np.unravel_index(np.argmax(ratio), ratio.shape)
        assert np.all(diff <= bound), (field, float(ratio[worst]), float(diff[worst]),
                                       float(bound[worst]))
    assert np.all(np3(b.shape == mi.ShapePtr(lg.shapes()[0]))[hit])
    assert type(b.bsdf()).__name__ != "NoneType"


def test06_uv_tangents_by_finite_differences():
    # Oracle: float64 finite differences of the documented uv map: move a hit
    # point along dp_du (dp_dv), project it back onto the ellipsoid along the
    # ray from the box centre (closed form), and read its uv: u (v) must grow
    # by the step, the other coordinate stay put.
    from lgshape.plugins import common
    a = np.array([1.6, 1.0, 0.7])                   # semi-axes
    T = mi.ScalarTransform4f().translate([0.5, 0, -0.3]) @ \
        mi.ScalarTransform4f().rotate([0, 0.6, 0.8], 30)
    lg = load_shape(expr=f"x^2/{a[0]**2} + y^2/{a[1]**2} + z^2/{a[2]**2} - 1",
                    bbox_min=list(-a - 0.1), bbox_max=list(a + 0.1), to_world=T)
    W = np.array(T.matrix, np.float64)
    si = common.ray_intersect(lg, rays(*random_rays(np.random.default_rng(3), 3000,
                                                    np.array([0.5, 0, -0.3]), spread=0.5)))
    p, uv = np3(si.p), np3(si.uv)
    ok = np3(si.is_valid()) & (uv[:, 1] > 0.1) & (uv[:, 1] < 0.9) \
        & (uv[:, 0] > 0.05) & (uv[:, 0] < 0.95)

    def uv_of(pw):
        q = (pw - W[:3, 3]) @ np.linalg.inv(W[:3, :3]).T
        q = q / np.sqrt(((q / a) ** 2).sum(1, keepdims=True))    # onto the ellipsoid
        u = np.arctan2(q[:, 1], q[:, 0]) / (2 * np.pi) % 1.0
        v = np.arccos(q[:, 2] / np.linalg.norm(q, axis=1)) / np.pi
        return np.stack([u, v], 1)

    assert np.abs(uv_of(p)[ok] - uv[ok]).max() < 1e-5
    h = 1e-4
    for k, field in enumerate(("dp_du", "dp_dv")):
        tangent = np3(getattr(si, field))
        duv = (uv_of(p + h * tangent) - uv_of(p - h * tangent)) / (2 * h)
        expect = np.zeros(2)
        expect[k] = 1
        assert np.abs(duv[ok] - expect).max() < 2e-2, field
        assert np.abs(np.einsum("ij,ij->i", tangent, np3(si.n))[ok]).max() < 1e-4 * \
            np.linalg.norm(tangent[ok], axis=1).max()


def test07_no_self_hit_from_spawned_rays():
    # Oracle: the sphere is convex, so rays spawned outwards from a hit miss it;
    # rays spawned inwards hit its far side at the float64 chord.
    from lgshape.plugins import common
    lg = load_shape(**{k: v for k, v in SPHERE.items() if k != "type"})
    ray = rays(*random_rays(np.random.default_rng(4), 4000, np.zeros(3), spread=0.55))
    si = common.ray_intersect(lg, ray)
    assert np3(si.is_valid()).all()               # every ray aims inside the ball
    out = si.spawn_ray(si.to_world(mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)))
    assert not np3(common.ray_intersect(lg, out).is_valid()).any()
    assert not np3(common.ray_test(lg, out)).any()
    inward = si.spawn_ray(ray.d)
    far = common.ray_intersect(lg, inward)
    o, d = np3(inward.o), np3(inward.d)
    b = (o * d).sum(1)
    chord = -b + np.sqrt(b * b - (o * o).sum(1) + 1)
    assert np3(far.is_valid()).all()
    assert np.abs(np3(far.t) - chord).max() < 1e-5


def test07b_self_hit_epsilon():
    """Rays starting exactly on the surface (origin at the hit point, no
    spawn offset) ignore hits closer than SELF_HIT_EPSILON x the world box
    diagonal, as documented; hits just beyond it are reported. Oracle: the
    unit sphere's closed-form roots in float64."""
    from lgshape.plugins import common
    from lgshape.plugins.lgsurface import SELF_HIT_EPSILON
    lg = load_shape(**{k: v for k, v in SPHERE.items() if k != "type"})
    eps = SELF_HIT_EPSILON * np.linalg.norm(np.full(3, 2.2))
    rng = np.random.default_rng(7)
    p = rng.normal(size=(2000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    out = p + 0.3 * rng.normal(size=p.shape)              # outward directions
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out = np.where((out * p).sum(1, keepdims=True) > 0.2, out, p)
    assert not np3(common.ray_intersect(lg, rays(p, out)).is_valid()).any()
    assert not np3(common.ray_test(lg, rays(p, out))).any()
    # inward from the surface: the far side (chord -2 p.d), never t ~ 0
    si = common.ray_intersect(lg, rays(p, -out))
    chord = 2 * (p * out).sum(1)
    assert np3(si.is_valid()).all() and np.abs(np3(si.t) - chord).max() < 1e-5
    # starting 3 eps before the surface along the normal: hit at 3 eps
    q = p * (1 + 3 * eps)
    si = common.ray_intersect(lg, rays(q, -p))
    assert np3(si.is_valid()).all() and np.abs(np3(si.t) - 3 * eps).max() < 1e-6


def test08_flip_normals():
    # Oracle: flipping negates n (the grad f direction) and nothing else.
    from lgshape.plugins import common
    props = {k: v for k, v in SPHERE.items() if k != "type"}
    ray = rays(*random_rays(np.random.default_rng(5), 500, np.zeros(3), spread=0.5))
    a = common.ray_intersect(load_shape(**props), ray)
    b = common.ray_intersect(load_shape(**props, flip_normals=True), ray)
    assert np.allclose(np3(a.n), -np3(b.n)) and np.allclose(np3(a.t), np3(b.t))
    assert np.allclose(np3(a.n), np3(a.p), atol=1e-5)    # outward on the unit sphere


# ---------------------------------------------------------------------------
#  Errors
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("props, message", [
    ({"expr": "x^2 + * y", "bbox_min": [-1] * 3, "bbox_max": [1] * 3},
     r"malformed 'expr': expected .* but found '\*' at position 7"),
    ({"expr": "x^2 + foo(y)", "bbox_min": [-1] * 3, "bbox_max": [1] * 3},
     r"malformed 'expr': unknown identifier 'foo' .* at position 7"),
    ({"surface": "doughnut"}, r"unknown surface 'doughnut'; the library has sphere, torus"),
    ({"expr": "x^2 + y^2 + z^2 - 1"}, r"an 'expr' needs a box: give 'bbox_min' and 'bbox_max'"),
    ({"expr": "x - 1", "bbox_min": [-1] * 3}, r"'bbox_max' is missing"),
    ({"surface": "torus", "bbox_min": [1] * 3, "bbox_max": [-1] * 3}, r"must be below 'bbox_max'"),
    ({"surface": "torus", "radius": 2.0}, r"unknown parameter 'radius'.*known parameters: .*R, r"),
    ({"expr": "x - 1", "bbox_min": [-1] * 3, "bbox_max": [1] * 3, "R": 1.0},
     r"unknown parameter 'R'"),
    ({"surface": "blobs", "centers": "0 0 0"}, r"'centers' of surface 'blobs' cannot be set"),
    ({"surface": "torus", "expr": "x"}, r"give one of 'expr', 'expr_file', 'surface' or "
                                        r"'primitives', not 'expr' and 'surface'"),
    ({}, r"needs 'expr' \(an expression\), 'expr_file', 'primitives' \(a primitives file\) "
         r"or 'surface'"),
    ({"surface": "sphere", "depth": 2.5}, r"'depth' must be a non-negative integer"),
    ({"surface": "sphere", "depth": 11}, r"lgsurface: depth must be between 2 and 10"),
    ({"surface": "sphere", "L": -1.0}, r"'L' must be a positive number"),
    ({"surface": "sphere", "light": {"type": "point"}},
     r"the emitter child 'light' \(PointLight\) cannot sit on a shape; only an 'area'"),
])
def test09_error_messages(props, message):
    # Oracle: the message names the offending parameter (and the position).
    with pytest.raises(RuntimeError, match=message):
        load_shape(**props)


def test10_error_messages_from_xml(tmp_path):
    # Oracle: the same messages reach a user of an XML file; the parse error
    # keeps its caret line.
    scene = tmp_path / "bad.xml"
    scene.write_text('<scene version="3.0.0"><shape type="lgsurface">'
                     '<string name="expr" value="sin(x"/>'
                     '<point name="bbox_min" value="-1,-1,-1"/>'
                     '<point name="bbox_max" value="1,1,1"/>'
                     '</shape></scene>')
    with pytest.raises(RuntimeError) as err:
        mi.load_file(str(scene))
    assert "expected ')' but found the end of the expression at position 6" in str(err.value)
    assert "sin(x\n" in str(err.value) and "     ^" in str(err.value)


@pytest.mark.parametrize("plugin, props, message", [
    ("lg_aov", {"aovs": "dd:dpth"}, r"unknown AOV type 'dpth'"),
    ("lg_aov", {"aovs": "depth"}, r"invalid AOV 'depth': expected <name>:<type>"),
    ("lg_path", {"max_depth": 4, "maxdepth": 3}, r"maxdepth"),
    ("lg_direct", {"shading_samples": 2, "bsdf_samples": 1}, r"either 'shading_samples'"),
])
def test11_integrator_errors(plugin, props, message):
    # Oracle: the message names the bad parameter or value.
    with pytest.raises(RuntimeError, match=message):
        mi.load_dict({"type": plugin, **props})
