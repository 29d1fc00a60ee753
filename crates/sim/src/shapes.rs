//! Analytic primitives the scene is built from, and a bounding-volume hierarchy over them.
//!
//! Everything here is in the world frame, metres. Shapes answer three questions: their bounds, the
//! first ray parameter at which a ray meets them, and whether a point lies within a clearance of
//! them (for the camera's free-space test).

use nalgebra::{Matrix3, Vector3};

/// Hits closer than this along a ray are ignored so a ray never re-hits its own start surface.
const T_EPSILON: f64 = 1e-7;

/// A ray with a unit direction; `inv_dir` speeds up the box slab test.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Ray {
    pub origin: Vector3<f64>,
    pub dir: Vector3<f64>,
    /// Single-precision copies for the BVH box tests: `t = bound * inv - origin * inv`.
    inv_dir_f32: [f32; 3],
    origin_times_inv_f32: [f32; 3],
}

impl Ray {
    pub fn new(origin: Vector3<f64>, dir: Vector3<f64>) -> Self {
        // Nudge zero components so inverses stay finite and box tests never see inf * 0.
        let safe = |d: f64| {
            if d.abs() < 1e-9 {
                1e-9f64.copysign(d)
            } else {
                d
            }
        };
        let inv_dir = [1.0 / safe(dir.x), 1.0 / safe(dir.y), 1.0 / safe(dir.z)];
        Self {
            origin,
            dir,
            inv_dir_f32: inv_dir.map(|v| v as f32),
            origin_times_inv_f32: [
                (origin.x * inv_dir[0]) as f32,
                (origin.y * inv_dir[1]) as f32,
                (origin.z * inv_dir[2]) as f32,
            ],
        }
    }

    pub fn at(&self, t: f64) -> Vector3<f64> {
        self.origin + self.dir * t
    }
}

/// Axis-aligned bounds, kept as plain arrays for the hot traversal loop.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Bounds {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl Bounds {
    pub fn empty() -> Self {
        Self {
            min: [f64::INFINITY; 3],
            max: [f64::NEG_INFINITY; 3],
        }
    }

    pub fn from_centre_half(centre: &Vector3<f64>, half: &Vector3<f64>) -> Self {
        Self {
            min: [centre.x - half.x, centre.y - half.y, centre.z - half.z],
            max: [centre.x + half.x, centre.y + half.y, centre.z + half.z],
        }
    }

    pub fn union(&self, other: &Bounds) -> Self {
        let mut out = *self;
        for i in 0..3 {
            out.min[i] = out.min[i].min(other.min[i]);
            out.max[i] = out.max[i].max(other.max[i]);
        }
        out
    }

    pub fn centroid(&self) -> [f64; 3] {
        [
            0.5 * (self.min[0] + self.max[0]),
            0.5 * (self.min[1] + self.max[1]),
            0.5 * (self.min[2] + self.max[2]),
        ]
    }

    pub fn centre(&self) -> Vector3<f64> {
        Vector3::from(self.centroid())
    }

    pub fn half(&self) -> Vector3<f64> {
        Vector3::from_fn(|i, _| 0.5 * (self.max[i] - self.min[i]))
    }

    /// True when `p` lies in the box grown by `margin_m`.
    pub fn contains_within(&self, p: &Vector3<f64>, margin_m: f64) -> bool {
        (0..3).all(|i| self.min[i] - margin_m <= p[i] && p[i] <= self.max[i] + margin_m)
    }

    pub fn overlaps(&self, other: &Bounds, margin_m: f64) -> bool {
        (0..3).all(|i| {
            self.min[i] - margin_m <= other.max[i] && other.min[i] - margin_m <= self.max[i]
        })
    }
}

/// One analytic solid or surface.
#[derive(Clone, Debug)]
pub(crate) enum Shape {
    /// Axis-aligned ellipsoid (fruit).
    Ellipsoid {
        centre: Vector3<f64>,
        radii: Vector3<f64>,
    },
    /// Ellipsoid with its own axes (capsicum lobes, calyces).
    OrientedEllipsoid(OrientedEllipsoid),
    /// Flat two-sided elliptical disc (leaf); `u`, `v` are unit in-plane axes, `normal = u × v`.
    Disc {
        centre: Vector3<f64>,
        normal: Vector3<f64>,
        u: Vector3<f64>,
        v: Vector3<f64>,
        half_u_m: f64,
        half_v_m: f64,
    },
    /// Capped cylinder (stems, poles, pipes).
    Cylinder(Cylinder),
}

/// Capped cylinder from `base` along the unit `axis`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Cylinder {
    pub base: Vector3<f64>,
    pub axis: Vector3<f64>,
    pub length_m: f64,
    pub radius_m: f64,
}

impl Cylinder {
    fn bounds(&self) -> Bounds {
        let (base, axis, radius_m) = (&self.base, &self.axis, self.radius_m);
        let top = base + axis * self.length_m;
        let half = Vector3::from_fn(|i, _| radius_m * (1.0 - axis[i] * axis[i]).max(0.0).sqrt());
        Bounds::from_centre_half(base, &half).union(&Bounds::from_centre_half(&top, &half))
    }

    /// Height of `p` along the axis from the base, and its offset from the axis.
    fn axial(&self, p: &Vector3<f64>) -> (f64, Vector3<f64>) {
        let rel = p - self.base;
        let h = rel.dot(&self.axis);
        (h, rel - self.axis * h)
    }

    fn normal_at(&self, p: &Vector3<f64>) -> Vector3<f64> {
        let (h, radial) = self.axial(p);
        let side_gap = (radial.norm() - self.radius_m).abs();
        let cap_gap = h.abs().min((h - self.length_m).abs());
        if cap_gap < side_gap {
            if h < 0.5 * self.length_m {
                -self.axis
            } else {
                self.axis
            }
        } else {
            radial.try_normalize(1e-15).unwrap_or(self.axis)
        }
    }

    /// Points along the axis, ends included, at most 5 mm apart: enough to place thin
    /// cylinders against other shapes.
    pub fn axis_points(&self) -> impl Iterator<Item = Vector3<f64>> + '_ {
        let n = (self.length_m / 0.005).ceil().max(1.0) as usize;
        (0..=n).map(move |i| self.base + self.axis * (self.length_m * i as f64 / n as f64))
    }

    /// True when the cylinder comes within `margin_m` of the box (tested at its axis points).
    pub fn passes_through(&self, b: &Bounds, margin_m: f64) -> bool {
        self.axis_points()
            .any(|p| b.contains_within(&p, margin_m + self.radius_m))
    }

    fn is_within(&self, p: &Vector3<f64>, clearance_m: f64) -> bool {
        let (h, radial) = self.axial(p);
        let dh = (-h).max(h - self.length_m).max(0.0);
        let dr = (radial.norm() - self.radius_m).max(0.0);
        dh * dh + dr * dr <= clearance_m * clearance_m
    }

    #[inline(always)]
    fn intersect(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        intersect_cylinder(
            ray,
            t_max,
            &self.base,
            &self.axis,
            self.length_m,
            self.radius_m,
        )
    }
}

/// Ellipsoid whose semi-axes lie along the columns of `axes` (orthonormal, right-handed), with
/// half-lengths `radii`: the points `centre + axes * q` with `|q / radii| <= 1`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct OrientedEllipsoid {
    pub centre: Vector3<f64>,
    pub axes: Matrix3<f64>,
    pub radii: Vector3<f64>,
}

impl OrientedEllipsoid {
    /// Maps a world offset from the centre to the frame where the ellipsoid is the unit sphere.
    pub fn unit_from_world(&self) -> Matrix3<f64> {
        Matrix3::from_diagonal(&self.radii.map(|r| 1.0 / r)) * self.axes.transpose()
    }

    /// The offset from the centre in the ellipsoid's own axes.
    fn local(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.axes.tr_mul(&(p - self.centre))
    }

    /// Exact box: along world axis `i` the half extent is `|row i of axes * diag(radii)|`.
    fn bounds(&self) -> Bounds {
        let half = Vector3::from_fn(|i, _| {
            (0..3)
                .map(|j| (self.axes[(i, j)] * self.radii[j]).powi(2))
                .sum::<f64>()
                .sqrt()
        });
        Bounds::from_centre_half(&self.centre, &half)
    }

    /// The point of the ellipsoid farthest along `dir` (a unit vector), and how far along `dir`
    /// it lies (the support function).
    pub fn support(&self, dir: &Vector3<f64>) -> (Vector3<f64>, f64) {
        let along = self.axes.tr_mul(dir).component_mul(&self.radii);
        let reach_m = along.norm();
        let local = (along / reach_m.max(1e-300)).component_mul(&self.radii);
        (
            self.centre + self.axes * local,
            self.centre.dot(dir) + reach_m,
        )
    }

    /// True for points inside or on the surface.
    #[cfg(test)]
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        self.local(p).component_div(&self.radii).norm_squared() <= 1.0
    }

    fn normal_at(&self, p: &Vector3<f64>) -> Vector3<f64> {
        let q = self
            .local(p)
            .component_div(&self.radii.component_mul(&self.radii));
        (self.axes * q)
            .try_normalize(1e-15)
            .unwrap_or_else(|| self.axes.column(2).into_owned())
    }

    fn is_within(&self, p: &Vector3<f64>, clearance_m: f64) -> bool {
        let grown = self.radii.add_scalar(clearance_m);
        self.local(p).component_div(&grown).norm_squared() <= 1.0
    }

    /// The parameters `(s0, s1)` between which the line `origin + s * dir` is inside, if it
    /// crosses the ellipsoid.
    pub fn chord(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<(f64, f64)> {
        let m = self.unit_from_world();
        let oc = m * (origin - self.centre);
        let d = m * dir;
        let (a, b, c) = (d.dot(&d), oc.dot(&d), oc.dot(&oc) - 1.0);
        let disc = b * b - a * c;
        (disc > 0.0 && a > 0.0).then(|| {
            let sq = disc.sqrt();
            ((-b - sq) / a, (-b + sq) / a)
        })
    }
}

impl Shape {
    pub fn bounds(&self) -> Bounds {
        match self {
            Shape::Ellipsoid { centre, radii } => Bounds::from_centre_half(centre, radii),
            Shape::OrientedEllipsoid(e) => e.bounds(),
            Shape::Disc {
                centre,
                u,
                v,
                half_u_m,
                half_v_m,
                ..
            } => {
                let half = Vector3::from_fn(|i, _| {
                    ((half_u_m * u[i]).powi(2) + (half_v_m * v[i]).powi(2)).sqrt()
                });
                Bounds::from_centre_half(centre, &half)
            }
            Shape::Cylinder(c) => c.bounds(),
        }
    }

    /// Unit surface normal at a point on the surface (outward for solids; either side for discs).
    pub fn normal_at(&self, p: &Vector3<f64>) -> Vector3<f64> {
        match self {
            Shape::Ellipsoid { centre, radii } => (p - centre)
                .component_div(&radii.component_mul(radii))
                .try_normalize(1e-15)
                .unwrap_or_else(Vector3::z),
            Shape::OrientedEllipsoid(e) => e.normal_at(p),
            Shape::Disc { normal, .. } => *normal,
            Shape::Cylinder(c) => c.normal_at(p),
        }
    }

    /// True when `p` is within `clearance_m` of the shape (or inside it). Ellipsoids and discs use a
    /// close approximation of the true distance, which is all the free-space test needs.
    pub fn is_within(&self, p: &Vector3<f64>, clearance_m: f64) -> bool {
        match self {
            Shape::Ellipsoid { centre, radii } => {
                let grown = radii.add_scalar(clearance_m);
                (p - centre).component_div(&grown).norm_squared() <= 1.0
            }
            Shape::OrientedEllipsoid(e) => e.is_within(p, clearance_m),
            Shape::Disc {
                centre,
                normal,
                u,
                v,
                half_u_m,
                half_v_m,
            } => {
                let rel = p - centre;
                let off_plane = rel.dot(normal);
                if off_plane.abs() > clearance_m {
                    return false;
                }
                let (s, w) = (rel.dot(u), rel.dot(v));
                let q = (s / half_u_m).powi(2) + (w / half_v_m).powi(2);
                let in_plane_gap = if q <= 1.0 {
                    0.0
                } else {
                    // Radial projection onto the ellipse boundary: exact for circles, close for leaves.
                    let scale = 1.0 / q.sqrt();
                    ((s - s * scale).powi(2) + (w - w * scale).powi(2)).sqrt()
                };
                off_plane * off_plane + in_plane_gap * in_plane_gap <= clearance_m * clearance_m
            }
            Shape::Cylinder(c) => c.is_within(p, clearance_m),
        }
    }
}

/// Smallest ray parameter in (epsilon, t_max) where the ray meets a capped cylinder.
#[inline]
fn intersect_cylinder(
    ray: &Ray,
    t_max: f64,
    base: &Vector3<f64>,
    axis: &Vector3<f64>,
    length_m: f64,
    radius_m: f64,
) -> Option<f64> {
    let oc = ray.origin - base;
    let d_axial = ray.dir.dot(axis);
    let o_axial = oc.dot(axis);
    let d_perp = ray.dir - axis * d_axial;
    let o_perp = oc - axis * o_axial;
    let mut best = t_max;
    let mut found = false;
    let a = d_perp.dot(&d_perp);
    if a > 1e-14 {
        let b = o_perp.dot(&d_perp);
        let c = o_perp.dot(&o_perp) - radius_m * radius_m;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let sq = disc.sqrt();
            for t in [(-b - sq) / a, (-b + sq) / a] {
                let h = o_axial + t * d_axial;
                if t > T_EPSILON && t < best && (0.0..=length_m).contains(&h) {
                    best = t;
                    found = true;
                    break;
                }
            }
        }
    }
    if d_axial.abs() > 1e-12 {
        for cap_h in [0.0, length_m] {
            let t = (cap_h - o_axial) / d_axial;
            if t > T_EPSILON && t < best {
                let q = o_perp + d_perp * t;
                if q.dot(&q) <= radius_m * radius_m {
                    best = t;
                    found = true;
                }
            }
        }
    }
    found.then_some(best)
}

/// Disc test with the in-plane axes pre-scaled by the half-sizes (see [`Prim::Disc`]).
#[inline(always)]
fn intersect_disc(
    ray: &Ray,
    t_max: f64,
    centre: &Vector3<f64>,
    normal: &Vector3<f64>,
    u_scaled: &Vector3<f64>,
    v_scaled: &Vector3<f64>,
) -> Option<f64> {
    let denom = ray.dir.dot(normal);
    if denom.abs() < 1e-12 {
        return None;
    }
    let to_centre = centre - ray.origin;
    let t = to_centre.dot(normal) / denom;
    if !(t > T_EPSILON && t < t_max) {
        return None;
    }
    let p = ray.dir * t - to_centre;
    let s = p.dot(u_scaled);
    let w = p.dot(v_scaled);
    (s * s + w * w <= 1.0).then_some(t)
}

/// Ellipsoid test with pre-inverted radii (see [`Prim::Ellipsoid`]).
#[inline(always)]
fn intersect_ellipsoid(
    ray: &Ray,
    t_max: f64,
    centre: &Vector3<f64>,
    inv_radii: &Vector3<f64>,
) -> Option<f64> {
    let oc = (ray.origin - centre).component_mul(inv_radii);
    let d = ray.dir.component_mul(inv_radii);
    unit_sphere_hit(&oc, &d, t_max)
}

/// Smallest ray parameter in (epsilon, t_max) where the ray `oc + t d` (both already mapped
/// into the frame where the ellipsoid is the unit sphere at the origin) meets that sphere.
#[inline(always)]
fn unit_sphere_hit(oc: &Vector3<f64>, d: &Vector3<f64>, t_max: f64) -> Option<f64> {
    let a = d.dot(d);
    let b = oc.dot(d);
    let c = oc.dot(oc) - 1.0;
    let disc = b * b - a * c;
    if disc < 0.0 || a <= 0.0 {
        return None;
    }
    let sq = disc.sqrt();
    let t0 = (-b - sq) / a;
    if t0 > T_EPSILON {
        return (t0 < t_max).then_some(t0);
    }
    let t1 = (-b + sq) / a;
    (t1 > T_EPSILON && t1 < t_max).then_some(t1)
}

/// Oriented ellipsoid test: the ray is mapped into the frame where the ellipsoid is the unit
/// sphere (see [`Prim::OrientedEllipsoid`]); ray parameters are the same in both frames.
#[inline(always)]
fn intersect_oriented_ellipsoid(
    ray: &Ray,
    t_max: f64,
    centre: &Vector3<f64>,
    unit_from_world: &Matrix3<f64>,
) -> Option<f64> {
    let oc = unit_from_world * (ray.origin - centre);
    let d = unit_from_world * ray.dir;
    unit_sphere_hit(&oc, &d, t_max)
}

/// A shape in the form the closest-hit loop tests fastest: divisions and per-test products that
/// depend only on the shape are done once, when the scene is built.
#[derive(Clone, Copy, Debug)]
enum Prim {
    Ellipsoid {
        centre: Vector3<f64>,
        inv_radii: Vector3<f64>,
    },
    OrientedEllipsoid {
        centre: Vector3<f64>,
        /// [`OrientedEllipsoid::unit_from_world`], inverted once at build time.
        unit_from_world: Matrix3<f64>,
    },
    Disc {
        centre: Vector3<f64>,
        normal: Vector3<f64>,
        /// `u / half_u`, `v / half_v`: in-plane coordinates scaled so the rim is at 1.
        u_scaled: Vector3<f64>,
        v_scaled: Vector3<f64>,
    },
    Cylinder(Cylinder),
}

impl Prim {
    fn of(shape: &Shape) -> Self {
        match shape {
            Shape::Ellipsoid { centre, radii } => Prim::Ellipsoid {
                centre: *centre,
                inv_radii: radii.map(|r| 1.0 / r),
            },
            Shape::OrientedEllipsoid(e) => Prim::OrientedEllipsoid {
                centre: e.centre,
                unit_from_world: e.unit_from_world(),
            },
            Shape::Disc {
                centre,
                normal,
                u,
                v,
                half_u_m,
                half_v_m,
            } => Prim::Disc {
                centre: *centre,
                normal: *normal,
                u_scaled: u / *half_u_m,
                v_scaled: v / *half_v_m,
            },
            Shape::Cylinder(c) => Prim::Cylinder(*c),
        }
    }

    /// Same contract as [`Shape::intersect`].
    #[inline(always)]
    fn intersect(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        match self {
            Prim::Disc {
                centre,
                normal,
                u_scaled,
                v_scaled,
            } => intersect_disc(ray, t_max, centre, normal, u_scaled, v_scaled),
            Prim::Ellipsoid { centre, inv_radii } => {
                intersect_ellipsoid(ray, t_max, centre, inv_radii)
            }
            Prim::OrientedEllipsoid {
                centre,
                unit_from_world,
            } => intersect_oriented_ellipsoid(ray, t_max, centre, unit_from_world),
            Prim::Cylinder(c) => c.intersect(ray, t_max),
        }
    }
}

#[inline(always)]
fn fmin(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

#[inline(always)]
fn fmax(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// Rays traced together by [`Bvh::closest_hits`]: a block of `PACKET_WIDTH` × `PACKET_HEIGHT`
/// pixels.
pub(crate) const PACKET_WIDTH: usize = 8;
pub(crate) const PACKET_HEIGHT: usize = 8;
pub(crate) const PACKET: usize = PACKET_WIDTH * PACKET_HEIGHT;

/// Lane value of [`Packet::hit`] when the lane hit no shape.
pub(crate) const NO_HIT: u32 = u32::MAX;

/// A packet of rays from one origin. Before tracing, `t[l]` is lane `l`'s search limit (a
/// negative limit switches the lane off); after, it is the closest hit's parameter and `hit[l]`
/// the shape's index (or [`NO_HIT`], leaving `t[l]` as it was).
#[derive(Clone, Debug)]
pub(crate) struct Packet {
    pub origin: Vector3<f64>,
    pub rays: [Ray; PACKET],
    pub t: [f64; PACKET],
    pub hit: [u32; PACKET],
}

impl Packet {
    /// A packet whose lanes are all off, with rays along +z.
    pub fn new(origin: Vector3<f64>) -> Self {
        Self {
            origin,
            rays: [Ray::new(origin, Vector3::z()); PACKET],
            t: [-1.0; PACKET],
            hit: [NO_HIT; PACKET],
        }
    }

    /// Runs `intersect` on every lane `hits` marks and keeps the closer hits, as shape `index`.
    #[inline(always)]
    fn each_lane(
        &mut self,
        hits: &[bool; PACKET],
        best_f32: &mut [f32; PACKET],
        index: u32,
        intersect: impl Fn(&Ray, f64) -> Option<f64>,
    ) {
        for l in 0..PACKET {
            if hits[l] {
                if let Some(t) = intersect(&self.rays[l], self.t[l]) {
                    self.t[l] = t;
                    best_f32[l] = t as f32;
                    self.hit[l] = index;
                }
            }
        }
    }

    /// Switches every lane off and forgets the hits, keeping the rays (valid, if stale).
    pub fn switch_off(&mut self) {
        self.t = [-1.0; PACKET];
        self.hit = [NO_HIT; PACKET];
    }
}

/// Node box in single precision, rounded outwards, for a compact and fast traversal.
#[derive(Clone, Copy, Debug)]
struct NodeBox {
    min: [f32; 3],
    max: [f32; 3],
}

impl NodeBox {
    fn from_bounds(b: &Bounds) -> Self {
        // 10 µm outward margin covers f32 rounding for scenes within a few hundred metres.
        Self {
            min: b.min.map(|v| (v - 1e-5) as f32),
            max: b.max.map(|v| (v + 1e-5) as f32),
        }
    }

    #[inline(always)]
    fn hit(&self, ray: &Ray, t_max: f32) -> Option<f32> {
        let inv = &ray.inv_dir_f32;
        let oi = &ray.origin_times_inv_f32;
        let x0 = self.min[0] * inv[0] - oi[0];
        let x1 = self.max[0] * inv[0] - oi[0];
        let y0 = self.min[1] * inv[1] - oi[1];
        let y1 = self.max[1] * inv[1] - oi[1];
        let z0 = self.min[2] * inv[2] - oi[2];
        let z1 = self.max[2] * inv[2] - oi[2];
        let t_near = fmax(fmax(fmin(x0, x1), fmin(y0, y1)), fmax(fmin(z0, z1), 0.0));
        let t_far = fmin(fmin(fmax(x0, x1), fmax(y0, y1)), fmin(fmax(z0, z1), t_max));
        (t_near <= t_far).then_some(t_near)
    }
}

#[derive(Clone, Copy, Debug)]
struct Node {
    bounds: NodeBox,
    /// Leaf: index of the first primitive. Interior: index of the right child (left is next).
    first_or_right: u32,
    /// Number of primitives in a leaf; 0 marks an interior node.
    count: u32,
    /// Interior: the axis the children were split along (the left child holds the lower part).
    split_axis: u8,
}

const MAX_LEAF_SIZE: usize = 4;
const SAH_BINS: usize = 16;
/// Cost of one shape test relative to one box test, for the surface-area heuristic.
const SHAPE_TEST_COST: f64 = 8.0;

fn half_area(b: &Bounds) -> f64 {
    let d = [
        b.max[0] - b.min[0],
        b.max[1] - b.min[1],
        b.max[2] - b.min[2],
    ];
    if d.iter().any(|x| *x < 0.0) {
        return 0.0;
    }
    d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
}

/// Binned surface-area-heuristic split. Reorders `order` so the left part comes first and returns
/// its length, or None when keeping a leaf is cheaper (or nothing separates the centroids).
fn sah_split(
    order: &mut [usize],
    bounds: &[Bounds],
    centroids: &[[f64; 3]],
) -> Option<(usize, u8)> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for &i in order.iter() {
        for a in 0..3 {
            lo[a] = lo[a].min(centroids[i][a]);
            hi[a] = hi[a].max(centroids[i][a]);
        }
    }
    let parent_area = half_area(
        &order
            .iter()
            .fold(Bounds::empty(), |acc, &i| acc.union(&bounds[i])),
    );
    let leaf_cost = SHAPE_TEST_COST * order.len() as f64;
    let bin_of = |c: f64, a: usize| -> usize {
        let extent = hi[a] - lo[a];
        (((c - lo[a]) / extent * SAH_BINS as f64) as usize).min(SAH_BINS - 1)
    };
    let mut best: Option<(f64, usize, usize)> = None;
    for a in 0..3 {
        if hi[a] - lo[a] <= 1e-12 {
            continue;
        }
        let mut bin_bounds = [Bounds::empty(); SAH_BINS];
        let mut bin_counts = [0usize; SAH_BINS];
        for &i in order.iter() {
            let b = bin_of(centroids[i][a], a);
            bin_bounds[b] = bin_bounds[b].union(&bounds[i]);
            bin_counts[b] += 1;
        }
        // Sweep from the right to get suffix areas, then from the left to evaluate each plane.
        let mut right_area = [0.0; SAH_BINS];
        let mut right_count = [0usize; SAH_BINS];
        let mut acc = Bounds::empty();
        let mut count = 0;
        for b in (1..SAH_BINS).rev() {
            acc = acc.union(&bin_bounds[b]);
            count += bin_counts[b];
            right_area[b] = half_area(&acc);
            right_count[b] = count;
        }
        let mut left = Bounds::empty();
        let mut left_count = 0;
        for b in 1..SAH_BINS {
            left = left.union(&bin_bounds[b - 1]);
            left_count += bin_counts[b - 1];
            if left_count == 0 || right_count[b] == 0 {
                continue;
            }
            let cost = 1.0
                + SHAPE_TEST_COST
                    * (half_area(&left) * left_count as f64
                        + right_area[b] * right_count[b] as f64)
                    / parent_area.max(1e-300);
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, a, b));
            }
        }
    }
    let (cost, axis, split_bin) = best?;
    if cost >= leaf_cost && order.len() <= 8 {
        return None;
    }
    order.sort_unstable_by_key(|&i| bin_of(centroids[i][axis], axis) >= split_bin);
    let mid = order
        .iter()
        .take_while(|&&i| bin_of(centroids[i][axis], axis) < split_bin)
        .count();
    (mid > 0 && mid < order.len()).then_some((mid, axis as u8))
}
const STACK_DEPTH: usize = 128;

/// Bounding-volume hierarchy over shapes, median split on the widest centroid axis.
#[derive(Clone, Debug, Default)]
pub(crate) struct Bvh {
    nodes: Vec<Node>,
    /// The shapes in hierarchy order, prepared for ray tests ([`Bvh::set_shapes`]).
    prims: Vec<Prim>,
}

impl Bvh {
    /// Builds the hierarchy and returns it with the permutation that orders the shapes for it:
    /// `order[k]` is the original index of the shape that must sit at position `k`.
    pub fn build(bounds: &[Bounds]) -> (Self, Vec<usize>) {
        let mut order: Vec<usize> = (0..bounds.len()).collect();
        let centroids: Vec<[f64; 3]> = bounds.iter().map(Bounds::centroid).collect();
        let mut bvh = Bvh::default();
        if !bounds.is_empty() {
            bvh.build_node(&mut order, 0, bounds, &centroids);
        }
        (bvh, order)
    }

    /// Stores the shapes, already in the order [`Bvh::build`] returned, for [`Bvh::closest_hit`].
    pub fn set_shapes(&mut self, ordered: &[Shape]) {
        self.prims = ordered.iter().map(Prim::of).collect();
    }

    fn build_node(
        &mut self,
        order: &mut [usize],
        start: usize,
        bounds: &[Bounds],
        centroids: &[[f64; 3]],
    ) {
        let index = self.nodes.len();
        let node_bounds = order
            .iter()
            .fold(Bounds::empty(), |acc, &i| acc.union(&bounds[i]));
        self.nodes.push(Node {
            bounds: NodeBox::from_bounds(&node_bounds),
            first_or_right: start as u32,
            count: order.len() as u32,
            split_axis: 0,
        });
        if order.len() <= MAX_LEAF_SIZE {
            return;
        }
        let Some((mid, axis)) = sah_split(order, bounds, centroids) else {
            return;
        };
        let (left, right) = order.split_at_mut(mid);
        self.build_node(left, start, bounds, centroids);
        let right_index = self.nodes.len() as u32;
        self.build_node(right, start + mid, bounds, centroids);
        self.nodes[index].first_or_right = right_index;
        self.nodes[index].count = 0;
        self.nodes[index].split_axis = axis;
    }

    /// Closest shape hit before `t_max`: (t, index into the ordered shapes). `hint` is a shape to
    /// test first (the neighbouring pixel's): a hit there bounds the traversal from the start so
    /// that everything behind it is skipped; the answer is the same with or without it. `stack`
    /// is scratch space reused across rays to avoid per-ray allocation.
    pub fn closest_hit(
        &self,
        ray: &Ray,
        t_max: f64,
        hint: Option<usize>,
        stack: &mut Vec<(u32, f32)>,
    ) -> Option<(f64, usize)> {
        let root = self.nodes.first()?;
        let mut best_t = t_max;
        let mut best = None;
        if let Some(h) = hint {
            if let Some(t) = self.prims.get(h).and_then(|p| p.intersect(ray, best_t)) {
                best_t = t;
                best = Some(h);
            }
        }
        let mut best_t_f32 = best_t as f32;
        stack.clear();
        if let Some(t) = root.bounds.hit(ray, best_t_f32) {
            stack.push((0, t));
        }
        while let Some((node_index, t_entry)) = stack.pop() {
            if t_entry > best_t_f32 {
                continue;
            }
            let Some(node) = self.nodes.get(node_index as usize) else {
                continue;
            };
            if node.count > 0 {
                let first = node.first_or_right as usize;
                let end = first + node.count as usize;
                for (k, prim) in self.prims.get(first..end).unwrap_or(&[]).iter().enumerate() {
                    if let Some(t) = prim.intersect(ray, best_t) {
                        best_t = t;
                        best_t_f32 = t as f32;
                        best = Some(first + k);
                    }
                }
                continue;
            }
            let left = node_index + 1;
            let right = node.first_or_right;
            let hit_of = |i: u32| {
                self.nodes
                    .get(i as usize)
                    .and_then(|n| n.bounds.hit(ray, best_t_f32))
            };
            // Push the farther child first so the nearer one is visited first and shrinks best_t.
            match (hit_of(left), hit_of(right)) {
                (Some(tl), Some(tr)) => {
                    if tl <= tr {
                        stack.push((right, tr));
                        stack.push((left, tl));
                    } else {
                        stack.push((left, tl));
                        stack.push((right, tr));
                    }
                }
                (Some(tl), None) => stack.push((left, tl)),
                (None, Some(tr)) => stack.push((right, tr)),
                (None, None) => {}
            }
        }
        best.map(|i| (best_t, i))
    }

    /// Closest hits of a packet of rays that share one origin (see [`Packet`]). Nodes are tested
    /// for all lanes at once, against each lane's own closest hit so far, so a lane never tests a
    /// shape its single-ray traversal would have skipped by distance; the answer per lane is the
    /// closest hit, as [`Bvh::closest_hit`] gives.
    pub fn closest_hits(&self, packet: &mut Packet, stack: &mut Vec<u32>) {
        if self.nodes.is_empty() {
            return;
        }
        let o = packet.origin.map(|v| v as f32);
        let mut inv = [[0f32; PACKET]; 3];
        let mut best_f32 = [0f32; PACKET];
        for l in 0..PACKET {
            for (a, lanes) in inv.iter_mut().enumerate() {
                lanes[l] = packet.rays[l].inv_dir_f32[a];
            }
            best_f32[l] = packet.t[l] as f32;
        }
        // Children are visited nearer first along their split axis, judged by the first lane.
        let dir_positive = [0, 1, 2].map(|a| packet.rays[0].dir[a] >= 0.0);
        stack.clear();
        stack.push(0);
        while let Some(node_index) = stack.pop() {
            let Some(node) = self.nodes.get(node_index as usize) else {
                continue;
            };
            let b = &node.bounds;
            let lo = [b.min[0] - o[0], b.min[1] - o[1], b.min[2] - o[2]];
            let hi = [b.max[0] - o[0], b.max[1] - o[1], b.max[2] - o[2]];
            let mut hits = [false; PACKET];
            for l in 0..PACKET {
                let (x0, x1) = (lo[0] * inv[0][l], hi[0] * inv[0][l]);
                let (y0, y1) = (lo[1] * inv[1][l], hi[1] * inv[1][l]);
                let (z0, z1) = (lo[2] * inv[2][l], hi[2] * inv[2][l]);
                let t_near = fmax(fmax(fmin(x0, x1), fmin(y0, y1)), fmax(fmin(z0, z1), 0.0));
                let t_far = fmin(
                    fmin(fmax(x0, x1), fmax(y0, y1)),
                    fmin(fmax(z0, z1), best_f32[l]),
                );
                hits[l] = t_near <= t_far;
            }
            if !hits.iter().any(|&h| h) {
                continue;
            }
            if node.count > 0 {
                let first = node.first_or_right as usize;
                let end = first + node.count as usize;
                for (k, prim) in self.prims.get(first..end).unwrap_or(&[]).iter().enumerate() {
                    let index = (first + k) as u32;
                    // One match per shape, not per lane.
                    match prim {
                        Prim::Disc {
                            centre,
                            normal,
                            u_scaled,
                            v_scaled,
                        } => packet.each_lane(&hits, &mut best_f32, index, |ray, t_max| {
                            intersect_disc(ray, t_max, centre, normal, u_scaled, v_scaled)
                        }),
                        Prim::Ellipsoid { centre, inv_radii } => {
                            packet.each_lane(&hits, &mut best_f32, index, |ray, t_max| {
                                intersect_ellipsoid(ray, t_max, centre, inv_radii)
                            })
                        }
                        Prim::OrientedEllipsoid {
                            centre,
                            unit_from_world,
                        } => packet.each_lane(&hits, &mut best_f32, index, |ray, t_max| {
                            intersect_oriented_ellipsoid(ray, t_max, centre, unit_from_world)
                        }),
                        Prim::Cylinder(_) => {
                            packet.each_lane(&hits, &mut best_f32, index, |ray, t_max| {
                                prim.intersect(ray, t_max)
                            })
                        }
                    }
                }
                continue;
            }
            let (left, right) = (node_index + 1, node.first_or_right);
            if dir_positive[usize::from(node.split_axis.min(2))] {
                stack.push(right);
                stack.push(left);
            } else {
                stack.push(left);
                stack.push(right);
            }
        }
    }

    /// True when any shape lies within `clearance_m` of `p`.
    pub fn any_within(&self, shapes: &[Shape], p: &Vector3<f64>, clearance_m: f64) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        let mut stack = [0u32; STACK_DEPTH];
        let mut sp = 1usize;
        while sp > 0 {
            sp -= 1;
            let node_index = stack[sp];
            let node = &self.nodes[node_index as usize];
            let b = &node.bounds;
            let inside = (0..3).all(|i| {
                p[i] >= b.min[i] as f64 - clearance_m && p[i] <= b.max[i] as f64 + clearance_m
            });
            if !inside {
                continue;
            }
            if node.count > 0 {
                let first = node.first_or_right as usize;
                if shapes[first..first + node.count as usize]
                    .iter()
                    .any(|s| s.is_within(p, clearance_m))
                {
                    return true;
                }
            } else if sp + 2 <= STACK_DEPTH {
                stack[sp] = node_index + 1;
                stack[sp + 1] = node.first_or_right;
                sp += 2;
            }
        }
        false
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use nalgebra::Rotation3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    fn random_unit(rng: &mut ChaCha8Rng) -> Vector3<f64> {
        loop {
            let v = Vector3::from_fn(|_, _| rng.gen_range(-1.0..1.0));
            if (0.01..1.0).contains(&v.norm_squared()) {
                return v.normalize();
            }
        }
    }

    /// Rays from points around `centre` towards points near it.
    fn rays_at(centre: &Vector3<f64>, rng: &mut ChaCha8Rng) -> Vec<Ray> {
        (0..500)
            .map(|_| {
                let origin = centre + random_unit(rng) * 0.3;
                let target = centre + random_unit(rng) * rng.gen_range(0.0..0.06);
                Ray::new(origin, (target - origin).normalize())
            })
            .collect()
    }

    #[test]
    fn an_oriented_ellipsoid_with_world_axes_is_the_axis_aligned_one() {
        let centre = Vector3::new(0.2, -0.1, 0.9);
        let radii = Vector3::new(0.03, 0.025, 0.04);
        let aligned = Shape::Ellipsoid { centre, radii };
        let oriented = Shape::OrientedEllipsoid(OrientedEllipsoid {
            centre,
            axes: Matrix3::identity(),
            radii,
        });
        let (a, o) = (Prim::of(&aligned), Prim::of(&oriented));
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut hits = 0;
        for ray in rays_at(&centre, &mut rng) {
            let (ta, to) = (a.intersect(&ray, 10.0), o.intersect(&ray, 10.0));
            assert_eq!(ta.is_some(), to.is_some());
            if let (Some(ta), Some(to)) = (ta, to) {
                hits += 1;
                assert!((ta - to).abs() < 1e-12);
                let p = ray.at(ta);
                assert!((aligned.normal_at(&p) - oriented.normal_at(&p)).norm() < 1e-9);
            }
            let p = ray.at(0.3);
            assert_eq!(aligned.is_within(&p, 0.05), oriented.is_within(&p, 0.05));
        }
        assert!(hits > 100, "{hits}");
        let (ba, bo) = (aligned.bounds(), oriented.bounds());
        assert_eq!((ba.min, ba.max), (bo.min, bo.max));
    }

    #[test]
    fn a_rotated_ellipsoid_is_hit_on_its_surface_with_its_normal_inside_its_bounds() {
        let e = OrientedEllipsoid {
            centre: Vector3::new(0.2, -0.1, 0.9),
            axes: Rotation3::from_euler_angles(0.5, -0.3, 1.2).into_inner(),
            radii: Vector3::new(0.05, 0.02, 0.03),
        };
        let shape = Shape::OrientedEllipsoid(e);
        let prim = Prim::of(&shape);
        let level = |p: &Vector3<f64>| e.local(p).component_div(&e.radii).norm_squared();
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut hits = 0;
        for ray in rays_at(&e.centre, &mut rng) {
            let Some(t) = prim.intersect(&ray, 10.0) else {
                continue;
            };
            hits += 1;
            let p = ray.at(t);
            assert!((level(&p) - 1.0).abs() < 1e-9, "{}", level(&p));
            // The normal is the level set's gradient, facing out.
            let n = shape.normal_at(&p);
            let h = 1e-7;
            let grad = Vector3::from_fn(|i, _| {
                let step = Vector3::from_fn(|j, _| if i == j { h } else { 0.0 });
                (level(&(p + step)) - level(&(p - step))) / (2.0 * h)
            });
            assert!((n - grad.normalize()).norm() < 1e-5);
            assert!(ray.dir.dot(&n) < 0.0, "the first hit faces the ray");
            assert!(shape.is_within(&p, 1e-9) && !shape.is_within(&(p + n * 0.002), 0.001));
        }
        assert!(hits > 100, "{hits}");
        // The box is tight: the outermost points along each world axis lie on its faces.
        let b = shape.bounds();
        for i in 0..3 {
            let axis = Vector3::from_fn(|j, _| if i == j { 1.0 } else { 0.0 });
            let (top, reach) = e.support(&axis);
            let (bottom, low) = e.support(&-axis);
            assert!((reach - b.max[i]).abs() < 1e-12 && (-low - b.min[i]).abs() < 1e-12);
            assert!((level(&top) - 1.0).abs() < 1e-9 && (level(&bottom) - 1.0).abs() < 1e-9);
        }
        // A chord's ends lie on the surface.
        let (s0, s1) = e.chord(&e.centre, &Vector3::z()).unwrap();
        for s in [s0, s1] {
            assert!((level(&(e.centre + Vector3::z() * s)) - 1.0).abs() < 1e-9);
        }
    }
}
