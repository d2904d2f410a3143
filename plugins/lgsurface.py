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

import difflib
import inspect
import math
import numbers
import os
import warnings

import numpy as np

import drjit as dr
import mitsuba as mi

import lgshape
from lgshape import surfaces
from lgshape.arraymath import DrJitMath
from lgshape.expr import evaluate, gradient
from lgshape.expr.node import topological
from lgshape.expr.ops import FUNCTIONS
from lgshape.expr.parser import free_names
from .area import replace_area_light
from .checks import LGShapeWarning

#: Relative distance (times the world box diagonal) below which a ray does not
#: report a hit: a ray spawned from the surface must not find the point it
#: left (the root search would find it again within its tolerance).
SELF_HIT_EPSILON = 1e-4

#: The ray flags that ask for uv, its tangents or the shading frame (else
#: :meth:`LGSurface.compute_surface_interaction` fills the minimal fields).
_SURFACE_FLAGS = int(mi.RayFlags.UV) | int(mi.RayFlags.dPdUV) | int(mi.RayFlags.ShadingFrame)

_OWN = ("expr", "expr_file", "surface", "primitives", "combine", "smoothness", "threshold",
        "bbox_min", "bbox_max", "L", "G", "depth", "to_world", "flip_normals")
#: Own parameters that only some ways of giving f read, and which those are.
_APPLIES = {"combine": "goes with 'primitives'",
            "smoothness": "goes with 'primitives' and combine 'smooth_union'",
            "threshold": "goes with 'primitives' and combine 'blend'",
            "bbox_min": "goes with 'bbox_max'", "bbox_max": "goes with 'bbox_min'"}


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
     * - (named constants)
       - |float|
       - Any other identifier of ``expr`` (or ``expr_file``) is a named
         constant bound to the number property of that name, e.g.
         ``expr="x^2 + y^2 + z^2 - radius^2"`` with
         ``<float name="radius" value="1"/>``. An identifier without such a
         property is an error naming it; a property the expression does not
         use is an unknown parameter.
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
       - Pruning depth: 2^depth cells per axis, 2 to 10. (Default: 7; 6 for
         expressions of over 128 nodes; for many primitives 6 to 8 by their number)
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
         periodic ones).
     * - (Nested plugin)
       - |emitter|
       - An ``area`` emitter: the surface emits light (on the side its
         normal points to), of a uniform or textured radiance (evaluated at
         the surface's uv). It is replaced by :class:`.area.LGAreaLight`
         (the same radiance and sampling weight), which the lg integrators
         sample themselves (:func:`.common.sample_emitter_direction`:
         Mitsuba's area emitter samples its shape in C++, which cannot reach
         this Python shape). Other emitter types are refused.

    The surface is rendered by the ``lg_path``, ``lg_direct``, ``lg_aov``,
    ``lg_volpath`` and ``lg_prb`` integrators; Mitsuba's own integrators (``path``, ``volpath``, ``prb``,
    ``direct``, ``aov``, ...) do not see it, and ``mi.render`` (wrapped by
    :func:`lgshape.register_plugins`) and ``lgshape render`` warn when one
    renders a scene with lgsurfaces (:mod:`lgshape.plugins.checks`).
    ``interior`` / ``exterior`` media are read as by any Mitsuba shape and
    rendered by ``lg_volpath`` (the other lg integrators ignore media, and
    warn where the scene has some).

    **Scene parameters.** ``mi.traverse`` shows ``<id>.to_world``
    (``AffineTransform4f``) and every numeric parameter of f as a float32
    ``Float``: a library surface's parameters (``<id>.R``), an expression's
    named constants (``<id>.radius``), a primitives file's ``smoothness`` or
    ``threshold``; and those of its BSDF (``<id>.bsdf....``) and media.
    The surface's own are differentiable (and discontinuous: they move
    silhouettes) under ``lg_prb`` where f holds them as named constants
    (``to_world`` and all of them but a library surface's parameter that only
    sets its box, e.g. ``gyroid.half_size``, which ``mi.traverse`` flags
    non-differentiable): the search stays detached and a hit is
    attached to them by the implicit-function theorem
    (:meth:`compute_surface_interaction`); other integrators refuse a
    render with a gradient on one
    (:class:`~lgshape.plugins.checks.NotDifferentiableError`). After
    ``params.update()`` a new value of a parameter of f builds a new
    :class:`lgshape.Surface` (its compiled kernels are reused: its
    constants are opaque), a new ``to_world`` only new matrices and bounds;
    the render then equals that of a scene loaded with the new values. A
    size of a library surface (``lgshape.surfaces.SIZES``: radius, R, r,
    half_size, ...) must be > 0, at load and at update. Where f has no zero
    in its box (no cell of the pruning grid is occupied), loading (or an
    update that leaves it so) warns once (:class:`~.checks.LGShapeWarning`). The
    placeholder triangle's keys (``vertex_positions``, ``faces``, ...) are
    not listed.

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
            if props.type(name) != mi.Properties.Type.Object or \
                    not isinstance(props.get(name), mi.Emitter):
                continue
            if props.get(name).class_name() != "AreaLight":
                raise ValueError(
                    f"lgsurface: the emitter child '{name}' "
                    f"({props.get(name).class_name()}) cannot sit on a shape; only an "
                    "'area' emitter can")
            # evaluated at this surface's uv, sampled by the lg integrators
            props[name] = replace_area_light(props.get(name))
        try:
            self._source = _read_surface(props)
            self._bbox_given = _read_bbox(props)
            self._hints = {"L": _positive(props, "L"), "G": _positive(props, "G"),
                           "depth": _depth(props)}
        except ValueError as err:        # (ParseError too): name the unknown keys as well
            raise _naming_unknown(err, props) from None
        to_world = props.get("to_world", mi.ScalarTransform4f())
        self.flip = bool(props.get("flip_normals", False))
        # The scene parameters (mi.traverse): Dr.Jit values that
        # SceneParameters writes in place; parameters_changed reads them.
        # to_world is held in float32, as by Mitsuba's own shapes (the
        # property may be float64), so that a loaded matrix and an updated
        # one go through the same rounding.
        m32 = np.array(to_world.matrix, dtype=np.float64).astype(np.float32)
        self._to_world = mi.AffineTransform4f(mi.ScalarTransform4f(m32))
        self._params = {k: mi.Float(v) for k, v in self._source.values.items()}
        #: How many Surfaces this shape has built (1 after loading; one more
        #: per update that changes a parameter of f, none for to_world).
        self.builds = 0
        self._mesh_traversal = False
        super().__init__("lgsurface", 3, 1, props)

        unknown = props.unqueried()
        unused = [k for k in unknown if k in _APPLIES]
        if unused:
            raise ValueError("lgsurface: " + "; ".join(
                f"'{k}' does not apply here: it {_APPLIES[k]}" for k in unused))
        if unknown:
            known = list(dict.fromkeys(list(_OWN) + list(self._source.values)))
            raise ValueError(_unknown_text(unknown, known) + self._source.hint)

        self._values = dict(self._source.values)        # the values in use
        self.surface, self.source = self._build(self._values)
        self._set_matrix(_matrix_of(self._to_world))
        # The placeholder: a zero-area triangle along the diagonal of the
        # world box (so the scene's bounds include the surface); Embree
        # never reports a hit on a triangle without area.
        self._set_placeholder(faces=True)
        super().parameters_changed(["vertex_positions", "faces"])

    # ---- Scene parameters (mi.traverse / params.update()) -------------------

    def traverse(self, callback):
        """The BSDF (and any emitter or medium) as children, with Mitsuba's flags, then
        ``to_world`` (an ``AffineTransform4f``) and every numeric parameter
        of f (a ``Float``: a library surface's parameters, an expression's
        named constants, a primitives file's ``smoothness``/``threshold``).
        ``to_world`` and the parameters that f holds as named constants
        (those ``lg_prb`` differentiates, :meth:`differentiable`) are flagged
        differentiable and discontinuous (they move the surface's
        silhouettes); the others (a library surface's parameter that only
        sets its box, such as ``gyroid.half_size``, or one its function
        computes with in Python) non-differentiable. The placeholder mesh's own parameters
        (``vertex_positions``, ``faces``, ...) are not listed: they are not
        the surface's (:meth:`_set_placeholder` reaches them)."""
        if self._mesh_traversal:
            return super().traverse(callback)
        for name, child in (("bsdf", self.bsdf()), ("emitter", self.emitter()),
                            ("interior_medium", self.interior_medium()),
                            ("exterior_medium", self.exterior_medium())):
            if child is not None:
                callback.put(name, child, mi.ParamFlags.Differentiable)
        flags = mi.ParamFlags.Differentiable | mi.ParamFlags.Discontinuous
        callback.put("to_world", self._to_world, flags)
        differentiable = self.differentiable()
        for name, value in self._params.items():
            callback.put(name, value, flags if name in differentiable
                         else mi.ParamFlags.NonDifferentiable)

    def differentiable(self) -> set:
        """The names of f's parameters that ``lg_prb`` differentiates: those
        f holds as named constants (a primitives file's ``smoothness`` as its
        constants k, 1/k and k/4). A gradient on another one is a
        :class:`~lgshape.plugins.checks.NotDifferentiableError`."""
        named = self._named_constants()
        return {k for k in self._params
                if k in named or (k == "smoothness" and {"k", "k_inverse", "k_quarter"} <= named)}

    def _named_constants(self) -> set:
        if getattr(self, "_ad", None) is None:
            f = self.surface.expr
            named = {n.param[0] for n in topological([f]) if n.op == "named"}
            self._ad = (f, list(gradient(f)), named)
        return self._ad[2]

    def gradient_keys(self) -> list:
        """The keys (as ``mi.traverse`` names them) of this surface's
        parameters that have gradients enabled."""
        values = {"to_world": self._to_world, **self._params}
        prefix = f"{self.id()}." if self.id() else ""
        return [f"{prefix}{k}" for k, v in values.items() if dr.grad_enabled(v)]

    def parameters_changed(self, keys=None):
        """Rebuild what changed: a new :class:`lgshape.Surface` where a
        parameter of f has a new value (compiled kernels are reused: its
        constants are opaque), only the matrices and bounds where ``to_world``
        alone changed. Invalid values raise ValueError and are put back."""
        keys = list(keys or [])
        if not hasattr(self, "surface"):                 # still loading
            return super().parameters_changed(keys)
        every = not keys                                 # Mitsuba: [] means everything
        names = [k for k in self._params if every or k in keys]
        try:
            values = dict(self._values)
            for k in names:
                values[k] = _read_value(k, self._params[k])
            matrix = (_matrix_of(self._to_world) if every or "to_world" in keys
                      else self.matrix)
            new_f = values != self._values
            new_world = not np.array_equal(matrix, self.matrix)
            surface, source = self._build(values) if new_f else (None, None)
            if new_world:
                _invert(matrix)                          # checks before changing anything
        except Exception:
            for k in names:                              # put the values in use back
                dr.disable_grad(self._params[k])
                mi.set_property(self._params[k], self._values[k])
            dr.disable_grad(self._to_world)
            mi.set_property(self._to_world, mi.ScalarTransform4f(self.matrix.astype(np.float32)))
            raise
        # the differentiable forms of f are those of the new values
        self._ad = None
        if new_f:
            self.surface, self.source, self._values = surface, source, values
        if new_world:
            self._set_matrix(matrix)
        elif new_f:
            self._set_matrix(self.matrix)                # the box may have changed
        base = [k for k in keys if k != "to_world" and k not in self._params]
        if new_f or new_world:
            self._set_placeholder()
            base.append("vertex_positions")
        if base or every:
            super().parameters_changed(base)

    def _build(self, values):
        """The Surface of f for these parameter values, and its description."""
        given = [k for k in ("L", "G") if self._hints.get(k) is not None]
        if given and values != self._source.values:
            raise ValueError(f"lgsurface: a hand-given {' and '.join(given)} bounds f for the "
                             "loaded parameters only: an update of f's parameters is refused "
                             f"(leave {' and '.join(given)} out to animate f)")
        implicit = self._source.build(values)
        bbox = self._bbox_given
        if bbox is None:
            bbox = getattr(implicit, "bbox", None)
            if bbox is None:
                raise ValueError("lgsurface: an 'expr' needs a box: give 'bbox_min' and "
                                 "'bbox_max' (points, e.g. <point name=\"bbox_min\" "
                                 "value=\"-1.5, -1.5, -1.5\"/>)")
        # A box that comes with f (a library surface) moves with its
        # parameters: its centre enters as a named constant, so that a new
        # value keeps the compiled kernels.
        hints = dict(self._hints)
        if self._bbox_given is None and self._source.values:
            hints["named_centre"] = True
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            try:
                surface = lgshape.Surface(implicit, bbox=bbox, **hints)
            except ValueError as err:
                raise ValueError(f"lgsurface: {err}") from None
        self.builds += 1
        empty = not _hittable(surface)
        if empty and not getattr(self, "_empty", False):
            # said once per load (and again only after an update that
            # empties a surface that had one): this warning stands for the
            # library's own about the same f (a constant one, say)
            lo, hi = surface.bbox
            name = f"'{self.id()}'" if self.id() else "(no id)"
            warnings.warn(
                f"lgsurface {name}: f has no zero in its box {_point(lo)} .. {_point(hi)} "
                f"(no cell of its pruning grid can hold f = 0): nothing of it can be hit and "
                f"it will be missing from the image; check f's constants and signs, or the "
                f"box (bbox_min / bbox_max)", LGShapeWarning, stacklevel=_caller_level())
        for w in said:        # the library's (lgshape.trace's EmptySurfaceWarning) stand aside
            library = w.category.__module__.startswith("lgshape.") and \
                not w.category.__module__.startswith("lgshape.plugins")
            if not (empty and library):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        self._empty = empty
        return surface, self._source.describe(values, implicit)

    def _set_matrix(self, matrix):
        """Object-to-world matrix (float64, 4x4): matrices, world box,
        bounding sphere; the Dr.Jit copies are made again on next use
        (:meth:`_matrices`)."""
        self.matrix = matrix
        self.inverse = _invert(matrix)
        self._world_box = _transform_box(self.matrix, self.surface.bbox)
        self._sphere = _bounding_sphere(self.surface, self.matrix)
        self._jit = None

    def bounding_sphere(self):
        """(centre, radius) in world space of a sphere that holds the
        surface: about the occupied cells of its pruning grid (where f can
        vanish), so tight to a cell. An area emitter on the surface is
        sampled in its cone (:func:`.common.sample_emitter_direction`)."""
        c, r = self._sphere
        return mi.Point3f(*(dr.opaque(mi.Float, float(v)) for v in c)), dr.opaque(mi.Float, r)

    def _set_placeholder(self, faces=False):
        lo, hi = self._world_box
        self._mesh_traversal = True                      # the mesh's own keys
        try:
            params = mi.traverse(self)
        finally:
            self._mesh_traversal = False
        params["vertex_positions"] = mi.Float([*lo, *hi, *lo])
        if faces:
            params["faces"] = mi.UInt32([0, 1, 2])

    def _shape_ptr(self):
        """This shape as an opaque ShapePtr: its registry id is data, not a
        literal of the kernel, so a process that registered its shapes in
        another order reuses the kernels cached on disk."""
        ptr = getattr(self, "_ptr", None)
        if ptr is None:
            ptr = self._ptr = mi.ShapePtr(self)
            dr.make_opaque(ptr)
        return ptr

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
        pi.shape = dr.select(hit, self._shape_ptr(), dr.zeros(mi.ShapePtr))
        return pi

    def compute_surface_interaction(self, ray: mi.Ray3f, pi, ray_flags=None, active=True):
        """A complete :class:`mitsuba.SurfaceInteraction3f` at ``pi.t`` along
        ``ray``; with ``ray_flags`` ``RayFlags.Minimal`` (no UV, dPdUV or
        ShadingFrame) only t, p, n, the frame about n and wi (uv 0, the
        tangents an orthonormal frame). Where this surface's parameters have
        gradients (and gradients are not suspended), t, p, n, uv and the
        tangents carry their derivatives (:meth:`_attach`)."""
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

        fs, ft = mi.coordinate_system(n)
        full = ray_flags is None or bool(int(ray_flags) & _SURFACE_FLAGS)
        if full:
            uv, dq_du, dq_dv, ok = _spherical_uv(q, self._centre(), grad)
            dp_du, dp_dv = _linear(W, dq_du), _linear(W, dq_dv)
            ok &= dr.isfinite(dr.squared_norm(dp_du) + dr.squared_norm(dp_dv))
            si.uv = mi.Point2f(uv)
        else:
            ok = mi.Bool(False)
            dp_du = dp_dv = fs
        si.dp_du = dr.select(ok, dp_du, fs)
        si.dp_dv = dr.select(ok, dp_dv, ft)
        si.sh_frame = mi.Frame3f(si.n)
        si.initialize_sh_frame()
        si.wi = si.to_local(-dr.normalize(ray.d))
        si.time = ray.time
        si.wavelengths = ray.wavelengths
        si.shape = dr.select(active, self._shape_ptr(), dr.zeros(mi.ShapePtr))
        si.prim_index = mi.UInt32(0)
        # (no gradients while they are suspended)
        if self.gradient_keys() or dr.grad_enabled(ray.o) or dr.grad_enabled(ray.d):
            self._attach(ray, si, ok, grad)
        return dr.select(active, si, dr.zeros(mi.SurfaceInteraction3f))

    # ---- Derivatives with respect to the scene parameters -------------------

    def _attach(self, ray, si, uv_ok, grad0):
        """Attach the hit to the parameters that have gradients and to the
        ray where it carries derivatives (in place): the search is not
        differentiated; t, p, n, uv and the tangents get the derivatives of
        the implicit-function theorem. With F(t, theta) =
        f(W(theta)^-1 (o + t d); theta), o and d the ray's (attached), the
        hit t0 (F = 0) moves by dt = -dF / (dF/dt):
        t = t0 - (F - F0) / (grad f . d_obj), whose value
        is t0 and whose derivative is that; the point o + t d, the normal
        (W^-T grad f at the moved point) and the uv follow from t. The values
        are those of the search (:func:`drjit.replace_grad`); only the
        derivatives are new. Lanes without a hit, or where a derivative is
        undefined (grad f . d = 0, grad f = 0, uv at a pole: ``uv_ok``),
        keep the detached values there, and every input of the derivatives
        is finite (a NaN partial times a zero adjoint would still be NaN).
        ``grad0``: grad f at the hit (its value: the slope dF/dt is a
        constant of the derivatives)."""
        f, grad_f, bound = self._ad_forms()
        m = DrJitMath(mi.Float, bound=bound)
        W = mi.Matrix4f(self._to_world.matrix)
        Winv = dr.rcp(W)
        o = mi.Vector3f(ray.o)
        d = mi.Vector3f(ray.d)
        o_obj, d_obj = _affine(Winv, o), _linear(Winv, d)
        t0 = dr.detach(si.t)
        ok = dr.isfinite(t0)
        t0 = dr.select(ok, t0, 0.0)
        q0 = o_obj + t0 * d_obj
        F = evaluate(f, _point_env(q0), m)
        slope = dr.detach(dr.dot(mi.Vector3f(grad0), d_obj))
        ok &= dr.isfinite(slope) & (slope != 0)
        t = t0 - (F - dr.detach(F)) / dr.select(ok, slope, 1.0)
        p = o + t * d
        q_a = _affine(Winv, p)
        grad = mi.Vector3f(evaluate(grad_f, _point_env(q_a), m))
        N = [[Winv[j][i] for j in range(3)] for i in range(3)]           # W^-T
        ng = _linear(N, grad)
        n2 = dr.squared_norm(ng)
        n_ok = ok & (dr.detach(n2) > 0) & dr.isfinite(dr.detach(n2))
        n = ng * dr.rsqrt(dr.select(n_ok, n2, 1.0))
        n = -n if self.flip else n
        uv_ok = uv_ok & n_ok
        q_s = dr.select(uv_ok, q_a, mi.Vector3f(*self._centre()) + 1.0)   # (finite partials)
        g_s = dr.select(uv_ok, grad, mi.Vector3f(1, 1, 1))
        uv, dq_du, dq_dv, _ = _spherical_uv(q_s, self._centre(), g_s)

        def attach(value, attached, where):
            return dr.replace_grad(value, dr.select(where, attached, dr.detach(value)))
        si.t = attach(si.t, t, ok)
        si.p = attach(si.p, mi.Point3f(p), ok)
        si.n = attach(si.n, mi.Normal3f(n), n_ok)
        si.uv = attach(si.uv, mi.Point2f(uv), uv_ok)
        si.dp_du = attach(si.dp_du, _linear(W, dq_du), uv_ok)
        si.dp_dv = attach(si.dp_dv, _linear(W, dq_dv), uv_ok)
        si.sh_frame = mi.Frame3f(si.n)
        si.initialize_sh_frame()
        si.wi = si.to_local(-dr.normalize(ray.d))

    def hit_shift(self, p, d, active=True):
        """How far a hit of this surface at the world point ``p`` (detached)
        moves along the ray direction ``d`` as the parameters with gradients
        move, by the implicit-function theorem: a Float whose value is 0 and
        whose derivative is -dF / (dF/dt) (:meth:`_attach`); 0 with no
        derivative where the surface has none or the slope is 0."""
        active = mi.Bool(active)
        if not self.gradient_keys():
            return mi.Float(0)
        f, _, bound = self._ad_forms()
        m = DrJitMath(mi.Float, bound=bound)
        W = mi.Matrix4f(self._to_world.matrix)
        Winv = dr.rcp(W)
        p, d = dr.detach(mi.Vector3f(p)), dr.detach(mi.Vector3f(d))
        q = _affine(Winv, p)
        F = evaluate(f, _point_env(q), m)
        grad = mi.Vector3f(self.surface.gradient(mi.Point3f(dr.detach(q))))
        slope = dr.detach(dr.dot(grad, _linear(Winv, d)))
        ok = active & dr.isfinite(slope) & (slope != 0) & dr.isfinite(dr.detach(F))
        return dr.select(ok, -(F - dr.detach(F)) / dr.select(ok, slope, 1.0), 0.0)

    def silhouette(self, ray: mi.Ray3f, t_hit, width, active=True, leaves=None, moving_ray=None,
                   weight=None):
        """The relaxed silhouette of this surface for rays that hit it at
        ``t_hit``: (S, w, t_exit, band). S is the signed distance proxy of
        the ray to the surface's silhouette, min over the ray's chord through
        the solid of f / |grad f| in world units (0 where the ray is tangent,
        below 0 where it crosses), attached to the parameters that have
        gradients (its value detached: by the envelope theorem the chord's
        minimiser need not move); ``w`` the band's weight on -width < S < 0
        (``weight``: :func:`band_weight` where None, for the surface's own
        shading seen across the band; :func:`edge_weight` for a jump that
        varies smoothly across it; each integrates to 1 across the band);
        ``t_exit`` where the ray leaves the solid (the
        background behind a grazing hit starts there); ``band`` the lanes
        with w > 0. A grazing hit's chord is found with the guaranteed search
        (the exit), its minimiser by bisection of dF/dt on it. ``leaves``
        (a :class:`.common.WideLeaves`): S is attached to wide copies of the
        parameters' values, for a backward pass that reduces their gradients
        in one kernel. ``moving_ray``: ``ray`` attached to what moves its
        ends (a shadow ray's shading point and light sample): S follows them
        too, at the chord's minimiser's fixed position along the ray (the
        envelope theorem again), on a surface whose own parameters have no
        gradients as well; ``ray`` itself must then be detached."""
        active = mi.Bool(active) & dr.isfinite(t_hit)
        o, d = dr.detach(mi.Vector3f(ray.o)), dr.detach(mi.Vector3f(ray.d))
        # the exit: the next root after the hit
        inner = mi.Ray3f(ray)
        inner.o = mi.Point3f(o + t_hit * d)
        inner.maxt = dr.inf
        t_rel, exits = self.intersect(inner, active)
        active &= exits
        t_exit = t_hit + t_rel
        W, Winv, N = self._matrices()
        d_obj = _linear(Winv, d)

        def proxy(t):
            """f / |grad f| (world units) at o + t d, and the slope dF/dt."""
            q = mi.Point3f(_affine(Winv, o + t * d))
            g = mi.Vector3f(self.surface.gradient(q))
            norm = dr.norm(_linear(N, g))
            return mi.Float(self.surface.value(q)) / dr.select(norm > 0, norm, 1.0), \
                dr.dot(g, d_obj)
        # S <= f / |grad f| anywhere on the chord: a chord whose middle is
        # deeper than the band is no grazing hit (most hits end here)
        active &= proxy(0.5 * (t_hit + t_exit))[0] > -width
        # the chord's minimiser: dF/dt < 0 at the entry, > 0 at the exit
        lo, hi = dr.select(active, t_hit, 0.0), dr.select(active, t_exit, 0.0)

        def body(lo, hi, k):
            mid = 0.5 * (lo + hi)
            up = proxy(mid)[1] > 0
            return dr.select(up, lo, mid), dr.select(up, mid, hi), k + 1
        lo, hi, _ = dr.while_loop((mi.Float(lo), mi.Float(hi), mi.UInt32(0)),
                                  lambda lo, hi, k: active & (k < 24), body,
                                  label="lgsurface: silhouette chord")
        t_star = 0.5 * (lo + hi)
        p_star = o + t_star * d
        q_star = mi.Point3f(_affine(Winv, p_star))
        g_world = dr.norm(_linear(N, mi.Vector3f(self.surface.gradient(q_star))))
        ok = active & (g_world > 0) & dr.isfinite(g_world)
        g_world = dr.select(ok, g_world, 1.0)
        S0 = mi.Float(self.surface.value(q_star)) / g_world
        S = S0
        if not dr.flag(dr.JitFlag.SymbolicScope):
            # (evaluated with the caller's next kernel: the derivatives'
            # kernels then do not search for the chord again)
            dr.schedule(t_star, p_star, g_world, ok, S0)
        # a static surface's S moves only with the ray's ends (``moving_ray``)
        ends_move = moving_ray is not None and (dr.grad_enabled(moving_ray.o)
                                                or dr.grad_enabled(moving_ray.d))
        moves = bool(self.gradient_keys())
        if moves or ends_move:
            f, _, bound = self._ad_forms()
            Wa_inv = dr.rcp(mi.Matrix4f(self._to_world.matrix))
            if leaves is not None and moves:
                bound = {k: leaves.wide(v) for k, v in bound.items()}
                Wa_inv = [[leaves.wide(Wa_inv[i][j]) for j in range(4)] for i in range(3)]
            m = DrJitMath(mi.Float, bound=bound)
            if moving_ray is not None:
                p_star = mi.Vector3f(moving_ray.o) + t_star * mi.Vector3f(moving_ray.d)
            q_a = _affine(Wa_inv, mi.Vector3f(p_star))
            S_a = evaluate(f, _point_env(q_a), m) / g_world
            S = dr.replace_grad(S0, dr.select(ok, S_a, 0.0))
        band = ok & (S0 < 0) & (S0 > -width)
        weight = weight or band_weight
        return S, dr.select(band, weight(S0, width), 0.0), t_exit, band

    def _ad_forms(self):
        """f and grad f as expressions of the object-space point, and the
        named constants of f set by the parameters that have gradients
        (name -> their Dr.Jit value). A parameter with a gradient that f
        does not hold as a named constant (a library surface that computes
        with it in Python) cannot be differentiated: an error names it."""
        from .checks import NotDifferentiableError
        self._named_constants()
        f, grad_f, named = self._ad
        bound = {}
        prefix = f"{self.id()}." if self.id() else ""
        for k, v in self._params.items():
            if not dr.grad_enabled(v):
                continue
            if k == "smoothness" and {"k", "k_inverse", "k_quarter"} <= named:
                bound.update(k=v, k_inverse=dr.rcp(v), k_quarter=0.25 * v)
            elif k in named:
                bound[k] = v
            else:
                raise NotDifferentiableError(
                    f"lgsurface: the parameter '{prefix}{k}' has a gradient enabled, but f does "
                    f"not hold it as a named constant ({self.source} computes with it in "
                    f"Python), so its derivative is not known: disable its gradient, or write f "
                    f"as an 'expr' with '{k}' as a named constant")
        return f, grad_f, bound

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

#: Names an expression's constant cannot take: the shape's own parameters and
#: the keys of the placeholder mesh (its own traversal; ``mi.traverse`` hides them).
_RESERVED = _OWN + ("faces", "vertex_positions", "vertex_normals", "vertex_texcoords",
                    "silhouette_sampling_weight", "bsdf")


class _Source:
    """How f is built from its numeric parameters (the scene parameters
    besides ``to_world``): ``values`` (name -> float, as loaded),
    ``build(values)`` -> an expression, library Implicit or table form,
    ``describe(values, built)`` -> text for ``to_string``."""

    def __init__(self, values, build, describe, hint=""):
        # float32, as the scene parameters hold them (and Mitsuba's shapes
        # theirs): a loaded value and the same value set by an update agree
        self.values = {k: float(np.float32(v)) for k, v in values.items()}
        self.build, self.describe = build, describe
        self.hint = hint        # appended to the unknown-parameter error


def _read_surface(props) -> _Source:
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
        return _read_expr(props, text, f"expr_file '{path}'", f"expression in '{path}'")
    if "expr" in props:
        text = props.get("expr")
        if not isinstance(text, str):
            raise ValueError(f"lgsurface: 'expr' must be a string (an expression in x, y, z), "
                             f"got {type(text).__name__} {text!r}")
        return _read_expr(props, text, f"expr '{text}'", "'expr'")
    if "surface" not in props:
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
    values = {}
    for p in numeric:
        values[p.name] = float(p.default)
        if p.name in props:
            v = props.get(p.name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise ValueError(f"lgsurface: parameter '{p.name}' of surface '{name}' "
                                 f"must be a number, got {v!r}")
            values[p.name] = float(v)

    def build(values):
        try:
            spec = fn(**values)
        except (ValueError, ZeroDivisionError, OverflowError) as err:
            if str(err).startswith(f"{name}: "):         # it names the parameter and value
                raise ValueError(f"lgsurface: {err}") from None
            args = ", ".join(f"{k}={v:g}" for k, v in values.items())
            raise ValueError(f"lgsurface: surface '{name}' with {args}: {err}") from None
        return _with_named_constants(fn, values, spec)

    def describe(values, _):
        return f"{name}({', '.join(f'{k}={v:g}' for k, v in values.items())})"
    return _Source(values, build, describe)


def _with_named_constants(fn, values, spec):
    """The library surface with its parameters as named constants in the
    expression (so that another value keeps the expression's structure and
    its compiled kernel), where the function builds its expression from them
    with arithmetic only; its box comes from the numbers. A function that
    computes with a parameter in Python (a square root, a comparison) keeps
    the numbers."""
    from lgshape.expr.node import named
    try:
        shaped = fn(**{k: named(k, v) for k, v in values.items()})
        if not isinstance(shaped.expr, lgshape.Expr):
            return spec
    except (TypeError, ValueError, ZeroDivisionError, OverflowError, AttributeError):
        return spec
    # the same function: equal values at sample points of the box
    lo, hi = (np.asarray(b, np.float64) for b in spec.bbox)
    p = lo + (hi - lo) * np.random.default_rng(0).uniform(0, 1, (64, 3))
    from lgshape.arraymath import NUMPY
    from lgshape.expr import evaluate
    env = {v: p[:, i] for i, v in enumerate("xyz")}
    with np.errstate(all="ignore"):
        a = np.broadcast_to(evaluate(spec.expr, env, NUMPY), 64)
        b = np.broadcast_to(evaluate(shaped.expr, env, NUMPY), 64)
    same = np.allclose(a, b, rtol=1e-12, atol=1e-12 * (1 + np.nanmax(np.abs(a), initial=0)),
                       equal_nan=True)
    return surfaces.Implicit(spec.name, shaped.expr, spec.bbox) if same else spec


def _read_expr(props, text, what, where) -> _Source:
    """An expression whose free identifiers are bound to number properties
    of the shape (its named constants)."""
    try:
        free = free_names(text)
    except lgshape.ParseError as err:
        raise _parse_error(err, f"lgsurface: malformed {where}: {err}") from None
    values = {}
    for name, pos in free:
        if name in _RESERVED:
            err = lgshape.ParseError(text, pos, f"the name {name!r} cannot be a named constant: "
                                     f"it is a parameter of lgsurface itself (one of "
                                     f"{', '.join(_RESERVED)}); rename the constant", name)
            raise _parse_error(err, f"lgsurface: malformed {where}: {err}")
        if name in props:
            v = props.get(name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) \
                    or not math.isfinite(float(v)):
                raise ValueError(f"lgsurface: '{name}' is a named constant of the expression "
                                 f"but its property is not a finite number: {v!r}")
            values[name] = float(v)
    unbound = [name for name, _ in free if name not in values]
    others = [k for k in props.keys() if k not in _RESERVED and k not in values
              and props.type(k) != mi.Properties.Type.Object]

    def build(values):
        try:
            return lgshape.parse(text, constants=values)
        except lgshape.ParseError as err:
            hint = "" if err.identifier is None else _identifier_hint(err, others)
            raise _parse_error(err, f"lgsurface: malformed {where}: {err}{hint}") from None
        except ValueError as err:
            raise ValueError(f"lgsurface: {where}: {err}") from None

    if unbound:          # the parser's error names the first one (before unknown parameters)
        build(values)

    def describe(values, _):
        return what + (f" with {', '.join(f'{k}={v:g}' for k, v in values.items())}"
                       if values else "")
    return _Source(values, build, describe,
                   " (a number property is a named constant only where the expression "
                   "uses its name)")


def _parse_error(err, message):
    """A :class:`lgshape.ParseError` like ``err`` (its text, position and
    identifier) with the message ``message``."""
    new = lgshape.ParseError.__new__(lgshape.ParseError)
    ValueError.__init__(new, message)
    new.text, new.pos, new.identifier = err.text, err.pos, err.identifier
    return new


def _identifier_hint(err, properties):
    """What an unknown identifier of an expression may be: a function the
    language lacks (it is called), or a named constant without its property
    (``properties``: the shape's other number properties, for a misspelt one)."""
    name = err.identifier
    if err.text[err.pos + len(name):].lstrip().startswith("("):
        close = difflib.get_close_matches(name, list(FUNCTIONS), n=1)
        return (f"\n  '{name}' is not a function of the expression language; its functions "
                f"are {', '.join(FUNCTIONS)}"
                + (f" (did you mean '{close[0]}'?)" if close else ""))
    close = difflib.get_close_matches(name, properties, n=1)
    return (f"\n  a named constant needs a number property of the shape, e.g. "
            f"<float name=\"{name}\" value=\"1\"/>"
            + (f" (the shape has a property '{close[0]}': a misspelling?)" if close else ""))


def _unknown_text(unknown, known):
    """'lgsurface: unknown parameter ...' naming the unknown keys, the
    closest known key of each where one is close, and the known keys."""
    def one(key):
        close = difflib.get_close_matches(key, known, n=1)
        return f"'{key}'" + (f" (did you mean '{close[0]}'?)" if close else "")
    return (f"lgsurface: unknown parameter{'s' if len(unknown) > 1 else ''} "
            f"{', '.join(one(k) for k in unknown)}; known parameters: {', '.join(known)}")


def _naming_unknown(err, props):
    """``err`` (raised while reading the properties), its message extended
    by the properties that no reading of them knows (``grid``, ``filename``,
    ...): those an error before the unknown-parameter check would hide."""
    if "expr_file" in props:
        return err              # (its named constants are in the file: not known here)
    known = list(_OWN)
    name = props.get("surface") if "surface" in props else None
    if isinstance(name, str) and name in surfaces.LIBRARY:
        known += list(inspect.signature(surfaces.LIBRARY[name]).parameters)
    if "expr" in props and isinstance(props.get("expr"), str):
        try:
            known += [n for n, _ in free_names(props.get("expr"))]
        except lgshape.ParseError:
            pass
    unknown = [k for k in props.keys() if k not in known and k not in _RESERVED
               and props.type(k) != mi.Properties.Type.Object]
    if unknown:
        text = _unknown_text(unknown, list(dict.fromkeys(known)))
        err.args = (f"{err}\n  also: {text[len('lgsurface: '):]}",)
    return err


def _hittable(surface) -> bool:
    """Can a ray hit ``surface``: does an occupied cell of its pruning grid
    (where f may vanish) meet its box? (The grid may be a cube about a flat
    box, with cells outside it.)"""
    grid = surface.grid
    cells = np.asarray(getattr(grid, "cells", np.zeros((1, 3))), np.float64).reshape(-1, 3)
    if len(cells) == 0:
        return False
    if not hasattr(grid, "cell_size"):
        return True
    size = np.asarray(grid.cell_size, np.float64)
    lo_c = np.asarray(grid.lo, np.float64) + cells * size
    lo, hi = (np.asarray(v, np.float64) for v in surface.bbox)
    return bool(np.any(np.all((lo_c <= hi) & (lo_c + size >= lo), axis=1)))


def _caller_level() -> int:
    """The ``stacklevel`` for a warning given in this module that points at
    the user's code: the first frame outside lgshape's plugins and Mitsuba
    (a load or ``params.update()`` call)."""
    import sys
    skip = (os.path.dirname(os.path.abspath(__file__)), os.path.dirname(mi.__file__))
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(skip):
        frame, level = frame.f_back, level + 1
    return level


def _point(p):
    return "(" + ", ".join(f"{float(v):g}" for v in p) + ")"


def _resolve(name, what):
    path = str(mi.file_resolver().resolve(name))
    if not os.path.isfile(path):
        raise ValueError(f"lgsurface: '{what}' file not found: {name}")
    return path


def _read_primitives(props) -> _Source:
    from lgshape import primitives
    path = _resolve(props.get("primitives"), "primitives")
    combine = props.get("combine", "union")
    values = {}
    if combine == "smooth_union":
        values["smoothness"] = _positive(props, "smoothness")
        if values["smoothness"] is None:
            raise ValueError("lgsurface: combine 'smooth_union' needs 'smoothness' (a radius)")
    elif combine == "blend":
        t = _positive(props, "threshold")
        values["threshold"] = float(inspect.signature(primitives.blend)
                                    .parameters["threshold"].default) if t is None else t
    for k in ("smoothness", "threshold"):
        if k in props and not ((k == "smoothness" and combine == "smooth_union")
                               or (k == "threshold" and combine == "blend")):
            raise ValueError(f"lgsurface: '{k}' does not apply to combine '{combine}'")

    def build(values):
        kw = {}
        for k, v in values.items():
            if not v > 0:
                raise ValueError(f"lgsurface: '{k}' must be a positive number, got {v!r}")
            kw["k" if k == "smoothness" else k] = v
        try:
            return primitives.load(path, combine, **kw)
        except ValueError as err:
            raise ValueError(f"lgsurface: {err}") from None

    def describe(values, tf):
        extra = "".join(f", {k}={v:g}" for k, v in values.items())
        return f"primitives '{os.path.basename(path)}' ({combine}{extra}, {tf.rows})"
    return _Source(values, build, describe)


def _read_bbox(props):
    """The box given by bbox_min / bbox_max, or None (then f brings one)."""
    given = [k in props for k in ("bbox_min", "bbox_max")]
    if all(given):
        lo, hi = (_read_point(props, k) for k in ("bbox_min", "bbox_max"))
        if not all(math.isfinite(v) for v in (*lo, *hi)):
            raise ValueError(f"lgsurface: the box must be finite, got 'bbox_min' {lo}, "
                             f"'bbox_max' {hi}")
        if not all(a < b for a, b in zip(lo, hi)):
            raise ValueError(f"lgsurface: 'bbox_min' {lo} must be below 'bbox_max' {hi} "
                             "on every axis")
        return lo, hi
    if any(given):
        missing = "bbox_max" if given[0] else "bbox_min"
        raise ValueError(f"lgsurface: '{missing}' is missing (give both bbox_min and bbox_max)")
    return None


def _read_point(props, key):
    """A point property (three numbers) as a tuple of floats."""
    v = props.get(key)
    try:
        point = tuple(float(c) for c in v)
    except (TypeError, ValueError):
        point = ()
    if isinstance(v, str) or len(point) != 3:
        raise ValueError(f"lgsurface: '{key}' must be a point (three numbers), got {v!r}")
    return point


def _read_value(name, value) -> float:
    """A scene parameter's new value: one finite number."""
    if dr.width(value) != 1:
        raise ValueError(f"lgsurface: parameter '{name}' must hold one value, "
                         f"got {dr.width(value)}")
    v = float(value[0])
    if not math.isfinite(v):
        raise ValueError(f"lgsurface: parameter '{name}' must be finite, got {v}")
    return v


def _matrix_of(transform) -> np.ndarray:
    """The 4x4 float64 matrix of a (width-1) AffineTransform4f."""
    m = np.array(transform.matrix, dtype=np.float64)
    if m.shape != (4, 4):
        if m.shape != (4, 4, 1):
            raise ValueError(f"lgsurface: 'to_world' must be one transform, got an array "
                             f"of shape {m.shape}")
        m = m[..., 0]
    if not np.all(np.isfinite(m)):
        raise ValueError("lgsurface: 'to_world' must be finite")
    return m


def _invert(matrix) -> np.ndarray:
    try:
        inverse = np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        inverse = np.full((4, 4), np.nan)
    if not np.all(np.isfinite(inverse)):
        raise ValueError("lgsurface: 'to_world' is not invertible")
    return inverse


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


def band_weight(S, width):
    """The weight that stands for delta(S) on the inside band -width < S < 0
    of a silhouette: 2 tri(S; width / 4) - tri(S; width), with tri(S; e) =
    2 / e (1 + S / e) on (-e, 0) (each integrates to 1). Near a smooth
    silhouette the radiance inside varies as sqrt(-S) (the normal turns as
    the square root of the distance), so one triangle's estimate is off by
    c sqrt(width); the combination (Richardson's, in sqrt(width)) cancels
    that term, leaving an error of order width."""
    def tri(e):
        return dr.select(S > -e, 2.0 / e * (1.0 + S / e), 0.0)
    return 2.0 * tri(0.25 * width) - tri(width)


def edge_weight(S, width):
    """The weight that stands for delta(S) on the inside band -width < S < 0
    of an edge across which the jump varies smoothly (a shadow's edge, a
    light's edge: what the occluded samples would bring does not depend on
    the occluder's shading): (4 - 6 u) / width with u = -S / width. It
    integrates to 1 and its first moment in S is 0, so the error of the
    band's slope in S (the jump's, and the band's length bending with the
    edge's curvature) cancels, leaving an error of order width^2; its mean
    square over the band is 4 / width^2 (:func:`band_weight`'s is 15.3 /
    width^2: that many times the variance)."""
    u = -S / width
    return dr.select((u > 0) & (u < 1), (4.0 - 6.0 * u) / width, 0.0)


def _bounding_sphere(surface, matrix):
    """The world-space centre and radius of a sphere holding the occupied
    fine cells of ``surface``'s grid (its box where there are none)."""
    grid = surface.grid
    cells = getattr(grid, "cells", None)
    if cells is None or len(cells) == 0:
        lo, hi = (np.asarray(v, np.float64) for v in surface.bbox)
        corners = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)]
                            for k in range(8)])
    else:
        size = np.asarray(grid.cell_size, np.float64)
        base = np.asarray(grid.lo, np.float64) + np.asarray(cells, np.float64) * size
        offs = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)], np.float64)
        corners = (base[:, None, :] + offs[None] * size).reshape(-1, 3)
        # the pruning grid may be a cube about the box: keep to the box
        lo, hi = (np.asarray(v, np.float64) for v in surface.bbox)
        corners = np.clip(corners, lo, hi)
    world = corners @ matrix[:3, :3].T + matrix[:3, 3]
    c = 0.5 * (world.min(0) + world.max(0))
    r = float(np.sqrt(((world - c) ** 2).sum(1).max()))
    return c, r * (1 + 1e-6) + 1e-12


def _point_env(q):
    return {"x": q[0], "y": q[1], "z": q[2]}


def _linear(M, v):
    return mi.Vector3f(*(M[i][0] * v[0] + M[i][1] * v[1] + M[i][2] * v[2] for i in range(3)))


def _affine(M, p):
    return mi.Vector3f(*(M[i][0] * p[0] + M[i][1] * p[1] + M[i][2] * p[2] + M[i][3]
                         for i in range(3)))


def _spherical_uv(q, c, grad):
    """uv = spherical angles of q about c, and the surface tangents dq/du, dq/dv
    in the plane orthogonal to ``grad``: solve [grad u; grad v; grad f] X = I.
    ``ok`` is false where that system is near singular: grad u and grad v
    are orthogonal and span the plane orthogonal to q - c, so its
    determinant over |grad u| |grad v| |grad f| is the cosine between
    grad f and q - c; below 1e-3 (a surface that q - c nearly grazes, e.g.
    a plane through c) the tangents and their derivatives would be
    rounding noise, as large as 1e3 times their size or more."""
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
    scale = dr.norm(a) * dr.norm(b) * dr.norm(g)
    ok = (rho2 > 0) & dr.isfinite(det) & (dr.abs(det) > 1e-3 * scale)
    inv = dr.rcp(det)
    return mi.Vector2f(u, v), dr.cross(b, g) * inv, dr.cross(g, a) * inv, ok
