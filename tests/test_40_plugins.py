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
    # Oracle: Mitsuba's sphere (radius 1.3, rotated and moved) and the same
    # sphere as an lgsurface agree on every field of the interaction.
    from lgshape.plugins import common
    T = mi.ScalarTransform4f().translate([0.3, -0.2, 0.1]) @ \
        mi.ScalarTransform4f().rotate([0.6, 0.8, 0], 40)
    native = mi.load_dict({"type": "scene", "s": {
        "type": "sphere", "to_world": T @ mi.ScalarTransform4f().scale(1.3)}})
    lg = load_shape(expr="x^2 + y^2 + z^2 - 1.69", bbox_min=[-1.4] * 3, bbox_max=[1.4] * 3,
                    to_world=T)
    ray = rays(*random_rays(np.random.default_rng(2), 4000, np.array([0.3, -0.2, 0.1])))
    a, b = native.ray_intersect(ray), common.ray_intersect(lg, ray)
    hit = np3(a.is_valid())
    assert np.array_equal(hit, np3(b.is_valid())) and hit.mean() > 0.5
    for field, tol in [("t", 1e-5), ("p", 1e-5), ("n", 1e-5), ("uv", 1e-5),
                       ("dp_du", 1e-4), ("dp_dv", 1e-4), ("wi", 1e-5)]:
        x, y = np3(getattr(a, field))[hit], np3(getattr(b, field))[hit]
        assert np.abs(x - y).max() < tol * max(1.0, np.abs(x).max()), field
    for axis in ("s", "t", "n"):
        x, y = np3(getattr(a.sh_frame, axis))[hit], np3(getattr(b.sh_frame, axis))[hit]
        assert np.abs(x - y).max() < 1e-4, axis
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
    ({"surface": "sphere", "light": {"type": "area"}},
     r"an emitter child \('light'\) is not supported"),
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
