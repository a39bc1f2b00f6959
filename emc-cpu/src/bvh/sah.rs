//! Surface-area-heuristic cost of a finished BVH, in `f64`: the quality figure every builder and
//! table of the project reports. Iterative traversal only (trees can be very deep).
#![forbid(unsafe_code)]

use super::node::Bvh;
use emc_core::Aabb;

/// Constants of the SAH cost: `ct` per inner node (traversal), `ci` per primitive (intersection).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SahConstants {
    /// Cost of one inner node visit (traversal).
    pub ct: f64,
    /// Cost of one primitive test (intersection).
    pub ci: f64,
}

impl SahConstants {
    /// The headline constants: `Ct = Ci = 1`.
    pub const HEADLINE: SahConstants = SahConstants { ct: 1.0, ci: 1.0 };
    /// The collapse constants of Karras–Aila / ATRBVH: `Ct = 1.2`, `Ci = 1`.
    pub const COLLAPSE: SahConstants = SahConstants { ct: 1.2, ci: 1.0 };
}

/// Surface area of a box in `f64` (0 for a flat box; an inverted box counts as 0).
#[inline]
pub fn area(b: &Aabb) -> f64 {
    b.area_f64()
}

/// SAH cost of `bvh`:
///
/// ```text
/// SAH = ( ct · Σ_{inner n} A(n)  +  ci · Σ_{leaf l} A(l) · |l| ) / A(root)
/// ```
///
/// The root is counted as an inner node (when it is one). Only nodes reachable from the root are
/// summed, in depth-first order (left before right), so the result does not depend on threads.
/// A node reached twice (a malformed tree) is summed once. When the root's area is 0 (all
/// primitives on one point or one axis-parallel plane of zero area) every box has area 0 and
/// the quotient is undefined; the cost is then evaluated as if every box had the same area:
/// `ct · #inner + ci · Σ_leaf |l|`. An empty BVH costs 0.
pub fn sah_cost(bvh: &Bvh, k: SahConstants) -> f64 {
    let n = bvh.nodes.len();
    if n == 0 || bvh.root as usize >= n {
        return 0.0;
    }
    let mut seen = vec![false; n];
    let mut stack = vec![bvh.root];
    let (mut inner_a, mut leaf_a) = (0.0f64, 0.0f64);
    let (mut inner_n, mut leaf_p) = (0.0f64, 0.0f64);
    while let Some(i) = stack.pop() {
        let Some(node) = bvh.nodes.get(i as usize) else {
            continue;
        };
        if std::mem::replace(&mut seen[i as usize], true) {
            continue;
        }
        let a = area(&node.bounds);
        if node.is_leaf() {
            let c = node.count() as f64;
            leaf_a += a * c;
            leaf_p += c;
        } else {
            inner_a += a;
            inner_n += 1.0;
            // Right pushed first so that the left subtree is summed first.
            stack.push(node.right());
            stack.push(node.left());
        }
    }
    let root_a = area(&bvh.nodes[bvh.root as usize].bounds);
    if root_a > 0.0 {
        (k.ct * inner_a + k.ci * leaf_a) / root_a
    } else {
        k.ct * inner_n + k.ci * leaf_p
    }
}

/// The headline SAH: `Ct = Ci = 1` (meaningful on trees with one primitive per leaf).
pub fn sah_headline(bvh: &Bvh) -> f64 {
    sah_cost(bvh, SahConstants::HEADLINE)
}

/// The collapsed-tree SAH: `Ct = 1.2`, `Ci = 1`.
pub fn sah_collapsed(bvh: &Bvh) -> f64 {
    sah_cost(bvh, SahConstants::COLLAPSE)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::node::Node;
    use glam::Vec3;

    fn bx(min: [f32; 3], max: [f32; 3]) -> Aabb {
        Aabb::new(Vec3::from(min), Vec3::from(max))
    }

    #[test]
    fn three_node_tree_by_hand() {
        // Root: unit cube, area 6. Left leaf: 1×1×0.5 box, area 2(0.5+0.5+1) = 4, two prims.
        // Right leaf: 0.5 cube, area 1.5, one prim.
        let nodes = vec![
            Node::inner(bx([0.0; 3], [1.0; 3]), 1, 2),
            Node::leaf(bx([0.0; 3], [1.0, 1.0, 0.5]), 0, 2),
            Node::leaf(bx([0.5; 3], [1.0; 3]), 2, 1),
        ];
        let bvh = Bvh {
            nodes,
            prim_indices: vec![0, 1, 2],
            root: 0,
        };
        let want = (1.2 * 6.0 + 4.0 * 2.0 + 1.5) / 6.0;
        assert!((sah_collapsed(&bvh) - want).abs() < 1e-12);
        let want1 = (6.0 + 4.0 * 2.0 + 1.5) / 6.0;
        assert!((sah_headline(&bvh) - want1).abs() < 1e-12);
    }

    #[test]
    fn single_leaf_and_flat_root() {
        let one = Bvh {
            nodes: vec![Node::leaf(bx([0.0; 3], [1.0; 3]), 0, 3)],
            prim_indices: vec![0, 1, 2],
            root: 0,
        };
        assert_eq!(sah_headline(&one), 3.0);
        let p = bx([1.0; 3], [1.0; 3]);
        let flat = Bvh {
            nodes: vec![
                Node::inner(p, 1, 2),
                Node::leaf(p, 0, 1),
                Node::leaf(p, 1, 1),
            ],
            prim_indices: vec![0, 1],
            root: 0,
        };
        assert_eq!(sah_cost(&flat, SahConstants::COLLAPSE), 1.2 + 2.0);
        assert_eq!(sah_headline(&Bvh::default()), 0.0);
    }
}
