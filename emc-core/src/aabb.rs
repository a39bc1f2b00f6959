//! The primitive box that every encoder consumes: six `f32`, 24 bytes, `#[repr(C)]` so that
//! SIMD paths and the hardware model can stream it as raw words.
#![forbid(unsafe_code)]

use glam::Vec3;

/// An axis-aligned bounding box in `f32`, as a triangle's vertices give it.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
#[repr(C)]
pub struct Aabb {
    /// Minimum corner.
    pub min: Vec3,
    /// Maximum corner.
    pub max: Vec3,
}

const _: () = assert!(core::mem::size_of::<Aabb>() == 24);

impl Aabb {
    /// An empty box (min = +inf, max = -inf), the identity of [`Aabb::union`].
    pub const EMPTY: Aabb = Aabb {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };

    /// A box from its two corners.
    #[inline]
    pub const fn new(min: Vec3, max: Vec3) -> Self {
        Aabb { min, max }
    }

    /// The box of a single point.
    #[inline]
    pub const fn point(p: Vec3) -> Self {
        Aabb { min: p, max: p }
    }

    /// The box of a triangle.
    #[inline]
    pub fn from_triangle(a: Vec3, b: Vec3, c: Vec3) -> Self {
        Aabb {
            min: a.min(b).min(c),
            max: a.max(b).max(c),
        }
    }

    /// The smallest box holding both.
    #[inline]
    pub fn union(&self, o: &Aabb) -> Aabb {
        Aabb {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }

    /// Grow to hold a point.
    #[inline]
    pub fn grow(&mut self, p: Vec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }

    /// True when every coordinate is finite.
    #[inline]
    pub fn is_finite(&self) -> bool {
        self.min.is_finite() && self.max.is_finite()
    }

    /// True when `min <= max` on every axis (a point counts as valid).
    #[inline]
    pub fn is_valid(&self) -> bool {
        self.min.cmple(self.max).all()
    }

    /// True when `o` lies inside `self` (closed boxes).
    #[inline]
    pub fn contains(&self, o: &Aabb) -> bool {
        self.min.cmple(o.min).all() && o.max.cmple(self.max).all()
    }

    /// Centre, exact in `f64` (the sum of two `f32` and a halving).
    #[inline]
    pub fn center_f64(&self) -> [f64; 3] {
        [
            (self.min.x as f64 + self.max.x as f64) * 0.5,
            (self.min.y as f64 + self.max.y as f64) * 0.5,
            (self.min.z as f64 + self.max.z as f64) * 0.5,
        ]
    }

    /// Squared diagonal length in `f64`, evaluated as `(dx*dx + dy*dy) + dz*dz` without FMA.
    /// This exact order is normative: the size channel's thresholds are derived from it.
    #[inline]
    pub fn diagonal_sq_f64(&self) -> f64 {
        let dx = self.max.x as f64 - self.min.x as f64;
        let dy = self.max.y as f64 - self.min.y as f64;
        let dz = self.max.z as f64 - self.min.z as f64;
        (dx * dx + dy * dy) + dz * dz
    }

    /// Surface area in `f64` (0 for an empty or flat box).
    #[inline]
    pub fn area_f64(&self) -> f64 {
        let dx = (self.max.x as f64 - self.min.x as f64).max(0.0);
        let dy = (self.max.y as f64 - self.min.y as f64).max(0.0);
        let dz = (self.max.z as f64 - self.min.z as f64).max(0.0);
        2.0 * (dx * dy + dy * dz + dz * dx)
    }
}
