//! The scene frame: the boxes that codes are normalised to, computed once per scene.
//! Positions are normalised per axis to the centroid box (by default); sizes to the diagonal `D`
//! of the union of primitive boxes. Non-finite input is refused here, once, with the index.
#![forbid(unsafe_code)]

use crate::aabb::Aabb;
use crate::error::Error;
use crate::layout::Normalization;

/// Bounds gathered over the primitives of a scene, in a form that parallel reductions can merge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneBounds {
    /// Minimum of the primitive centres (exact in `f64`).
    pub centroid_min: [f64; 3],
    /// Maximum of the primitive centres.
    pub centroid_max: [f64; 3],
    /// Union of the primitive boxes.
    pub prim: Aabb,
    /// Number of primitives gathered.
    pub count: usize,
}

impl Default for SceneBounds {
    fn default() -> Self {
        SceneBounds::EMPTY
    }
}

impl SceneBounds {
    /// No primitive yet.
    pub const EMPTY: SceneBounds = SceneBounds {
        centroid_min: [f64::INFINITY; 3],
        centroid_max: [f64::NEG_INFINITY; 3],
        prim: Aabb::EMPTY,
        count: 0,
    };

    /// Add one primitive box; `index` names it in the error when it is not finite or inverted.
    #[inline]
    pub fn add(&mut self, b: &Aabb, index: usize) -> Result<(), Error> {
        if !b.is_finite() {
            return Err(Error::NonFinite(index));
        }
        if !b.is_valid() {
            return Err(Error::InvertedBox(index));
        }
        let c = b.center_f64();
        for (a, &ca) in c.iter().enumerate() {
            self.centroid_min[a] = self.centroid_min[a].min(ca);
            self.centroid_max[a] = self.centroid_max[a].max(ca);
        }
        self.prim = self.prim.union(b);
        self.count += 1;
        Ok(())
    }

    /// Bounds of a slice; `base` is the index of `boxes[0]` for error messages.
    pub fn of(boxes: &[Aabb], base: usize) -> Result<SceneBounds, Error> {
        let mut s = SceneBounds::EMPTY;
        for (i, b) in boxes.iter().enumerate() {
            s.add(b, base + i)?;
        }
        Ok(s)
    }

    /// Merge two partial results (commutative and associative: min/max/sum only).
    pub fn merge(&self, o: &SceneBounds) -> SceneBounds {
        let mut r = *self;
        for a in 0..3 {
            r.centroid_min[a] = r.centroid_min[a].min(o.centroid_min[a]);
            r.centroid_max[a] = r.centroid_max[a].max(o.centroid_max[a]);
        }
        r.prim = r.prim.union(&o.prim);
        r.count += o.count;
        r
    }
}

/// Where a scene's codes live: the position box (origin and per-axis extent) and the size
/// normaliser `D`. Built once per scene; every encoder of every layout shares it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    bounds: SceneBounds,
    normalization: Normalization,
    origin: [f64; 3],
    extent: [f64; 3],
    diag: f64,
}

impl Frame {
    /// The frame of a slice of primitive boxes, positions normalised to the centroid box.
    pub fn new(boxes: &[Aabb]) -> Result<Frame, Error> {
        Frame::with_normalization(boxes, Normalization::CentroidBox)
    }

    /// The frame of a slice of primitive boxes with a chosen position normalisation.
    pub fn with_normalization(boxes: &[Aabb], n: Normalization) -> Result<Frame, Error> {
        Frame::from_bounds(SceneBounds::of(boxes, 0)?, n)
    }

    /// The frame from bounds gathered elsewhere (for example by a parallel reduction).
    pub fn from_bounds(bounds: SceneBounds, normalization: Normalization) -> Result<Frame, Error> {
        if bounds.count == 0 {
            return Err(Error::EmptyScene);
        }
        let p = bounds.prim;
        let pmin = [p.min.x as f64, p.min.y as f64, p.min.z as f64];
        let pmax = [p.max.x as f64, p.max.y as f64, p.max.z as f64];
        let (origin, extent) = match normalization {
            Normalization::CentroidBox => {
                let o = bounds.centroid_min;
                let e = [
                    bounds.centroid_max[0] - o[0],
                    bounds.centroid_max[1] - o[1],
                    bounds.centroid_max[2] - o[2],
                ];
                (o, e)
            }
            Normalization::PrimitiveBox => (
                pmin,
                [pmax[0] - pmin[0], pmax[1] - pmin[1], pmax[2] - pmin[2]],
            ),
            Normalization::Cube => {
                let o = bounds.centroid_min;
                let e = [
                    bounds.centroid_max[0] - o[0],
                    bounds.centroid_max[1] - o[1],
                    bounds.centroid_max[2] - o[2],
                ];
                let m = e[0].max(e[1]).max(e[2]);
                (o, [m, m, m])
            }
        };
        let d = [pmax[0] - pmin[0], pmax[1] - pmin[1], pmax[2] - pmin[2]];
        let diag = libm::sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]);
        Ok(Frame {
            bounds,
            normalization,
            origin,
            extent,
            diag,
        })
    }

    /// The bounds the frame was built from.
    #[inline]
    pub fn bounds(&self) -> &SceneBounds {
        &self.bounds
    }

    /// The position normalisation.
    #[inline]
    pub fn normalization(&self) -> Normalization {
        self.normalization
    }

    /// Origin of the position box (what a zero coordinate means).
    #[inline]
    pub fn origin(&self) -> [f64; 3] {
        self.origin
    }

    /// Per-axis extent of the position box (0 on a flat axis).
    #[inline]
    pub fn extent(&self) -> [f64; 3] {
        self.extent
    }

    /// Diagonal `D` of the union of primitive boxes (the size normaliser).
    #[inline]
    pub fn diagonal(&self) -> f64 {
        self.diag
    }

    /// Number of primitives the frame was built from.
    #[inline]
    pub fn count(&self) -> usize {
        self.bounds.count
    }
}
