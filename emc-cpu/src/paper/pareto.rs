//! The Pareto front of `emc paper`'s accuracy-versus-time table: among configurations of one
//! scene, those no other configuration beats on both of two costs (lower is better on both).
#![forbid(unsafe_code)]

/// Flags, one per point, true where no other point is at most as costly on both axes and
/// strictly cheaper on one. Equal points are all on the front; a point with a NaN coordinate
/// is never on it and never dominates.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<bool> {
    points
        .iter()
        .map(|&(a, b)| {
            if a.is_nan() || b.is_nan() {
                return false;
            }
            !points.iter().any(|&(x, y)| dominates((x, y), (a, b)))
        })
        .collect()
}

/// True when `p` is at most `q` on both axes and strictly below on one.
pub fn dominates(p: (f64, f64), q: (f64, f64)) -> bool {
    p.0 <= q.0 && p.1 <= q.1 && (p.0 < q.0 || p.1 < q.1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dominance_is_strict_on_one_axis() {
        assert!(dominates((1.0, 1.0), (1.0, 2.0)));
        assert!(!dominates((1.0, 2.0), (1.0, 2.0)));
        assert!(!dominates((0.5, 3.0), (1.0, 2.0)));
        assert!(!dominates((f64::NAN, 0.0), (1.0, 2.0)));
    }
}
