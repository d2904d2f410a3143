"""The ``lgsurface`` shape: an implicit surface f(x, y, z) = 0 in a Mitsuba scene.

Mitsuba 3.9.1 cannot trace Python shapes through Embree/OptiX, so the shape is
a :class:`mitsuba.Mesh` subclass holding one degenerate triangle that no ray
ever hits: it gives XML and ``mi.load_dict`` a shape type, carries the BSDF,
puts the surface's box into the scene's bounds, and is what ``si.shape``
points at. The rays themselves are traced by :class:`lgshape.Surface` through
the ``lg_*`` integrators (:mod:`.common`). The methods follow the interface of
upstream Python shapes (``ray_intersect_preliminary``,
``compute_surface_interaction``, ``bbox``), so the class can become a real
shape once a Mitsuba release traces Python shapes.
"""
from __future__ import annotations

import inspect
import math
import numbers
import os

import numpy as np

import drjit as dr
import mitsuba as mi

import lgshape
from lgshape import surfaces

#: Relative distance (times the world box diagonal) below which a ray does not
#: report a hit: a ray spawned from the surface must not find the point it
#: left (the root search would find it again within its tolerance).
SELF_HIT_EPSILON = 1e-4

_OWN = ("expr", "expr_file", "surface", "primitives", "combine", "smoothness", "threshold",
        "bbox_min", "bbox_max", "L", "G", "depth", "to_world", "flip_normals")


class LGSurface(mi.Mesh):
    r"""
    .. _shape-lgsurface:

    Implicit surface (:monosp:`lgsurface`)
    --------------------------------------

    .. pluginparameters::

     * - expr
       - |string|
       - The function f(x, y, z) in lgshape's expression language, e.g.
         ``x^2 + y^2 + z^2 - 1``. The surface is f = 0; the normal points
         towards f > 0. Give either ``expr`` or ``surface``.
     * - surface
       - |string|
       - A surface of the library (``lgshape.surfaces.LIBRARY``: sphere,
         torus, tangle, barth_sextic, kummer, chmutov6, clebsch, blobs,
         gyroid, spikes). Its numeric parameters are plain properties named
         as in the Python function, e.g. ``<float name="R" value="1"/>`` for
         the torus.
     * - expr_file
       - |string|
       - A file holding the expression (any length; found like Mitsuba's
         other files, e.g. beside the scene).
     * - primitives
       - |string|
       - A primitives file (:func:`lgshape.primitives.load`: one primitive
         per line, ``sphere cx cy cz r``, ``capsule ax ay az bx by bz r``,
         ``box cx cy cz hx hy hz [rounding]``, ``torus cx cy cz R r``,
         optionally ``w=weight``), combined by ``combine``: ``union``
         (default), ``smooth_union`` (radius ``smoothness``) or ``blend``
         (soft objects, iso-level ``threshold``, default 0.5). The box
         defaults to the primitives' extent. Thousands of primitives are
         fine: each pruning cell evaluates only those that matter there.
     * - bbox_min, bbox_max
       - |point|
       - The box, in object space, outside which the surface is clipped.
         Required with ``expr``; library surfaces bring a default.
     * - L, G
       - |float|
       - Optional hand-given bounds: a Lipschitz constant of f over the box,
         and a bound of \|d^2 f(o + t d) / dt^2\| for unit d (see
         :class:`lgshape.Surface`). By default both are computed.
     * - depth
       - |int|
       - Pruning depth: 2^depth cells per axis, 2 to 10. (Default: 6)
     * - to_world
       - |transform|
       - Any affine object-to-world transform. The ray search runs in object
         space; distances stay world distances.
     * - flip_normals
       - |bool|
       - Point the normals towards f < 0. (Default: |false|)
     * - (Nested plugin)
       - |bsdf|
       - The surface's BSDF (default: ``diffuse``). Mitsuba's BSDFs are
         one-sided: the front is the side the normal points to. Wrap the BSDF
         in ``twosided`` for surfaces seen from both sides (open, clipped or
         periodic ones). Area emitters are not supported.

    The surface is rendered by the ``lg_path``, ``lg_direct`` and ``lg_aov``
    integrators; Mitsuba's own integrators do not see it.

    **uv parameterization.** ``uv`` are the spherical angles of the object
    space point about the centre c of the box, with the convention of
    Mitsuba's ``sphere``: u = atan2(y - c_y, x - c_x) / 2 pi in [0, 1) and
    v = acos((z - c_z) / \|p - c\|) / pi in [0, 1]. ``dp_du`` and ``dp_dv``
    are the surface tangents of this parameterization (the tangent vectors
    along which u, respectively v, grows by one while the other stays fixed).
    Where the direction from c grazes the surface, or at the poles, they
    fall back to an orthonormal tangent frame.

    .. tabs::

        .. code-tab:: xml

            <shape type="lgsurface">
                <string name="surface" value="torus"/>
                <float name="R" value="1"/>
                <float name="r" value="0.35"/>
                <transform name="to_world"><rotate x="1" angle="60"/></transform>
                <bsdf type="diffuse"/>
            </shape>

        .. code-tab:: python

            'type': 'lgsurface',
            'expr': 'x^2 + y^2 + z^2 - 1',
            'bbox_min': [-1.1, -1.1, -1.1],
            'bbox_max': [1.1, 1.1, 1.1],
    """

    IS_LGSURFACE = True  # how :func:`.common.lg_shapes` recognises it

    def __init__(self, props: mi.Properties):
        for name in props.keys():
            if props.type(name) == mi.Properties.Type.Object and \
                    isinstance(props.get(name), mi.Emitter):
                raise ValueError(
                    f"lgsurface: an emitter child ('{name}') is not supported: the "
                    "surface cannot emit light. Light the scene with a native shape "
                    "(e.g. a 'rectangle' with an 'area' emitter) or an environment.")
        self.source, implicit, params = _read_surface(props)
        bbox = _read_bbox(props, implicit)
        hints = {"L": _positive(props, "L"), "G": _positive(props, "G"),
                 "depth": _depth(props)}
        to_world = props.get("to_world", mi.ScalarTransform4f())
        self.flip = bool(props.get("flip_normals", False))
        super().__init__("lgsurface", 3, 1, props)

        unknown = props.unqueried()
        if unknown:
            known = ", ".join(list(_OWN) + list(params))
            raise ValueError(f"lgsurface: unknown parameter '{unknown[0]}'"
                             f"{' (and ' + ', '.join(unknown[1:]) + ')' if unknown[1:] else ''}"
                             f"; known parameters: {known}")

        try:
            self.surface = lgshape.Surface(implicit, bbox=bbox, **hints)
        except ValueError as err:
            raise ValueError(f"lgsurface: {err}") from None

        self.matrix = np.array(to_world.matrix, dtype=np.float64)
        self.inverse = np.linalg.inv(self.matrix)
        if not np.all(np.isfinite(self.inverse)):
            raise ValueError("lgsurface: 'to_world' is not invertible")
        self._world_box = _transform_box(self.matrix, self.surface.bbox)
        self._jit = None

        # The placeholder: a zero-area triangle along the diagonal of the
        # world box (so the scene's bounds include the surface); Embree
        # never reports a hit on a triangle without area.
        lo, hi = self._world_box
        params_ = mi.traverse(self)
        params_["vertex_positions"] = mi.Float([*lo, *hi, *lo])
        params_["faces"] = mi.UInt32([0, 1, 2])
        params_.update()

    # ---- Upstream Python-shape interface -----------------------------------

    def bbox(self, prim_index=None) -> mi.ScalarBoundingBox3f:
        """World-space bounds of the (clipped) surface."""
        lo, hi = self._world_box
        return mi.ScalarBoundingBox3f(lo, hi)

    def primitive_count(self) -> int:
        return 1

    def ray_intersect_preliminary(self, ray: mi.Ray3f, prim_index=0, active=True):
        """The nearest hit in (ε, ray.maxt] with ε = SELF_HIT_EPSILON times the
        box diagonal (in world distance): ``t`` is inf where there is none."""
        t, hit = self.intersect(ray, active)
        pi = dr.zeros(mi.PreliminaryIntersection3f)
        pi.t = t
        pi.prim_index = mi.UInt32(0)
        pi.shape = dr.select(hit, mi.ShapePtr(self), dr.zeros(mi.ShapePtr))
        return pi

    def compute_surface_interaction(self, ray: mi.Ray3f, pi, ray_flags=None, active=True):
        """A complete :class:`mitsuba.SurfaceInteraction3f` at ``pi.t`` along
        ``ray`` (``ray_flags`` is accepted for the interface; all fields are
        always filled)."""
        active = mi.Bool(active) & dr.isfinite(pi.t)
        W, Winv, N = self._matrices()
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.t = dr.select(active, pi.t, dr.inf)
        si.p = ray(pi.t)
        q = _affine(Winv, mi.Point3f(si.p))                         # object-space point
        grad = self.surface.gradient(mi.Point3f(q))
        n = dr.normalize(_linear(N, grad))                          # inverse transpose
        n = dr.select(dr.isfinite(n), n, mi.Vector3f(0, 0, 1))
        n = -n if self.flip else n
        si.n = mi.Normal3f(n)

        uv, dq_du, dq_dv, ok = _spherical_uv(q, self._centre(), grad)
        dp_du, dp_dv = _linear(W, dq_du), _linear(W, dq_dv)
        fs, ft = mi.coordinate_system(n)
        ok &= dr.isfinite(dr.squared_norm(dp_du) + dr.squared_norm(dp_dv))
        si.uv = mi.Point2f(uv)
        si.dp_du = dr.select(ok, dp_du, fs)
        si.dp_dv = dr.select(ok, dp_dv, ft)
        si.sh_frame = mi.Frame3f(si.n)
        si.initialize_sh_frame()
        si.wi = si.to_local(-dr.normalize(ray.d))
        si.time = ray.time
        si.wavelengths = ray.wavelengths
        si.shape = dr.select(active, mi.ShapePtr(self), dr.zeros(mi.ShapePtr))
        si.prim_index = mi.UInt32(0)
        return dr.select(active, si, dr.zeros(mi.SurfaceInteraction3f))

    # ---- The ray queries in object space ------------------------------------

    def intersect(self, ray: mi.Ray3f, active=True):
        """(t, hit) of the nearest hit in (ε, ray.maxt], in units of ray.d."""
        o, d, t_min = self._object_ray(ray)
        return self.surface.intersect(o, d, t_min, ray.maxt, active)

    def occluded(self, ray: mi.Ray3f, active=True):
        """Is there any hit in (ε, ray.maxt]? (Stops at the first one found.)"""
        o, d, t_min = self._object_ray(ray)
        return self.surface.occluded(o, d, ray.maxt, active, t_min=t_min)

    def _object_ray(self, ray):
        _, Winv, _ = self._matrices()
        o = _affine(Winv, ray.o)
        d = _linear(Winv, ray.d)          # not renormalised: t stays valid
        t_min = self._eps / dr.norm(ray.d)
        return mi.Point3f(o), mi.Vector3f(d), t_min

    def _matrices(self):
        if self._jit is None:
            op = lambda v: dr.opaque(mi.Float, float(v))  # noqa: E731
            W = [[op(self.matrix[i, j]) for j in range(4)] for i in range(3)]
            Winv = [[op(self.inverse[i, j]) for j in range(4)] for i in range(3)]
            N = [[op(self.inverse[j, i]) for j in range(3)] for i in range(3)]
            diag = float(np.linalg.norm(np.subtract(*self._world_box[::-1])))
            self._eps = op(SELF_HIT_EPSILON * diag)
            lo, hi = self.surface.bbox
            self._c = [op(0.5 * (a + b)) for a, b in zip(lo, hi)]
            self._jit = (W, Winv, N)
        return self._jit

    def _centre(self):
        self._matrices()
        return self._c

    def to_string(self) -> str:
        lo, hi = self.surface.bbox
        m = "\n".join("               " + " ".join(f"{v:9.4g}" for v in row) for row in self.matrix)
        return (f"LGSurface[\n  surface = {self.source},\n  bbox = {lo} .. {hi},\n"
                f"  flip_normals = {self.flip},\n  to_world =\n{m},\n"
                f"  bsdf = {self.bsdf()}\n]")


# ---- Reading the properties -------------------------------------------------

def _read_surface(props):
    """-> (description, expression or Implicit, names of the library parameters)."""
    given = [k for k in ("expr", "expr_file", "surface", "primitives") if k in props]
    if len(given) > 1:
        raise ValueError(f"lgsurface: give one of 'expr', 'expr_file', 'surface' or "
                         f"'primitives', not {' and '.join(repr(k) for k in given)}")
    if "primitives" in props:
        return _read_primitives(props)
    if "expr_file" in props:
        path = _resolve(props.get("expr_file"), "expr_file")
        with open(path) as fh:
            text = fh.read()
        try:
            return f"expr_file '{path}'", lgshape.parse(text), ()
        except lgshape.ParseError as err:
            raise ValueError(f"lgsurface: malformed expression in '{path}': {err}") from None
    has_expr, has_surface = "expr" in props, "surface" in props
    if has_expr:
        text = props.get("expr")
        try:
            return f"expr '{text}'", lgshape.parse(text), ()
        except lgshape.ParseError as err:
            raise ValueError(f"lgsurface: malformed 'expr': {err}") from None
    if not has_surface:
        raise ValueError("lgsurface: needs 'expr' (an expression), 'expr_file', 'primitives' "
                         f"(a primitives file) or 'surface' (one of {', '.join(surfaces.LIBRARY)})")
    name = props.get("surface")
    if name not in surfaces.LIBRARY:
        raise ValueError(f"lgsurface: unknown surface '{name}'; the library has "
                         f"{', '.join(surfaces.LIBRARY)}")
    fn = surfaces.LIBRARY[name]
    numeric = [p for p in inspect.signature(fn).parameters.values()
               if isinstance(p.default, numbers.Real)]
    fixed = [p.name for p in inspect.signature(fn).parameters.values() if p not in numeric]
    for p in fixed:
        if p in props:
            raise ValueError(f"lgsurface: parameter '{p}' of surface '{name}' cannot be "
                             "set from a scene; use the Python API")
    kwargs = {}
    for p in numeric:
        if p.name in props:
            v = props.get(p.name)
            if not isinstance(v, numbers.Real):
                raise ValueError(f"lgsurface: parameter '{p.name}' of surface '{name}' "
                                 f"must be a number, got {v!r}")
            kwargs[p.name] = float(v)
    args = ", ".join(f"{k}={v:g}" for k, v in kwargs.items())
    return f"{name}({args})", fn(**kwargs), tuple(p.name for p in numeric)


def _resolve(name, what):
    path = str(mi.Thread.thread().file_resolver().resolve(name))
    if not os.path.isfile(path):
        raise ValueError(f"lgsurface: '{what}' file not found: {name}")
    return path


def _read_primitives(props):
    from lgshape import primitives
    path = _resolve(props.get("primitives"), "primitives")
    combine = props.get("combine", "union")
    kw = {}
    if combine == "smooth_union":
        kw["k"] = _positive(props, "smoothness")
        if kw["k"] is None:
            raise ValueError("lgsurface: combine 'smooth_union' needs 'smoothness' (a radius)")
    elif combine == "blend" and "threshold" in props:
        kw["threshold"] = _positive(props, "threshold")
    for k in ("smoothness", "threshold"):
        if k in props and not ((k == "smoothness" and combine == "smooth_union")
                               or (k == "threshold" and combine == "blend")):
            raise ValueError(f"lgsurface: '{k}' does not apply to combine '{combine}'")
    try:
        tf = primitives.load(path, combine, **kw)
    except ValueError as err:
        raise ValueError(f"lgsurface: {err}") from None
    return f"primitives '{os.path.basename(path)}' ({combine}, {tf.rows})", tf, ()


def _read_bbox(props, implicit):
    given = [k in props for k in ("bbox_min", "bbox_max")]
    if all(given):
        lo, hi = (tuple(float(v) for v in props.get(k)) for k in ("bbox_min", "bbox_max"))
        if not all(a < b for a, b in zip(lo, hi)):
            raise ValueError(f"lgsurface: 'bbox_min' {lo} must be below 'bbox_max' {hi} "
                             "on every axis")
        return lo, hi
    if any(given):
        missing = "bbox_max" if given[0] else "bbox_min"
        raise ValueError(f"lgsurface: '{missing}' is missing (give both bbox_min and bbox_max)")
    if isinstance(implicit, surfaces.Implicit) or getattr(implicit, "bbox", None) is not None:
        return implicit.bbox
    raise ValueError("lgsurface: an 'expr' needs a box: give 'bbox_min' and 'bbox_max' "
                     "(points, e.g. <point name=\"bbox_min\" value=\"-1.5, -1.5, -1.5\"/>)")


def _positive(props, name):
    if name not in props:
        return None
    v = props.get(name)
    if not isinstance(v, numbers.Real) or not (math.isfinite(v) and v > 0):
        raise ValueError(f"lgsurface: '{name}' must be a positive number, got {v!r}")
    return float(v)


def _depth(props):
    if "depth" not in props:
        return None
    v = props.get("depth")
    if not isinstance(v, numbers.Real) or v != int(v) or v < 0:
        raise ValueError(f"lgsurface: 'depth' must be a non-negative integer, got {v!r}")
    return int(v)


# ---- Geometry helpers ---------------------------------------------------------

def _transform_box(matrix, box):
    """World AABB of an object-space box under an affine matrix."""
    lo, hi = (np.asarray(v, dtype=np.float64) for v in box)
    corners = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)])
    world = corners @ matrix[:3, :3].T + matrix[:3, 3]
    return tuple(map(float, world.min(0))), tuple(map(float, world.max(0)))


def _linear(M, v):
    return mi.Vector3f(*(M[i][0] * v[0] + M[i][1] * v[1] + M[i][2] * v[2] for i in range(3)))


def _affine(M, p):
    return mi.Vector3f(*(M[i][0] * p[0] + M[i][1] * p[1] + M[i][2] * p[2] + M[i][3]
                         for i in range(3)))


def _spherical_uv(q, c, grad):
    """uv = spherical angles of q about c, and the surface tangents dq/du, dq/dv
    in the plane orthogonal to ``grad``: solve [grad u; grad v; grad f] X = I."""
    x, y, z = q[0] - c[0], q[1] - c[1], q[2] - c[2]
    rho2 = dr.fma(x, x, y * y)
    r2 = rho2 + z * z
    rho = dr.sqrt(rho2)
    phi = dr.atan2(y, x)
    u = dr.select(phi < 0, phi + 2 * dr.pi, phi) * dr.inv_two_pi
    v = dr.acos(dr.clip(z * dr.rsqrt(r2), -1, 1)) * dr.inv_pi
    a = mi.Vector3f(-y, x, 0) / (2 * dr.pi * rho2)                  # grad u
    b = mi.Vector3f(x * z / rho, y * z / rho, -rho) / (dr.pi * r2)  # grad v
    g = mi.Vector3f(grad)
    det = dr.dot(a, dr.cross(b, g))
    ok = (rho2 > 0) & (det != 0) & dr.isfinite(det)
    inv = dr.rcp(det)
    return mi.Vector2f(u, v), dr.cross(b, g) * inv, dr.cross(g, a) * inv, ok
