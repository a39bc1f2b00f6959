//! Apetrei 2014: the same binary radix tree as Karras, built bottom-up in one pass that also
//! finishes bounds, counts and the collapse decision (builder `lbvh-apetrei`). Internal node `k`
//! is the split between sorted positions `k` and `k + 1`; the root is whichever split is last.
#![forbid(unsafe_code)]

use std::sync::atomic::{AtomicU32, Ordering};

use emc_core::Aabb;
use rayon::prelude::*;

use super::refit::{zeroed, CollapseParams, RadixTree, LEAVES_PER_TASK, NONE};
use crate::sort::RadixKey;

/// Distance between the index-augmented keys at `k` and `k + 1`: the XOR of the keys, then (for
/// equal keys) the XOR of the positions. Smaller means a longer common prefix; compared as a
/// pair it orders exactly like Karras' δ (two boundary distances of a node never tie).
///
/// ```text
///   Δ(k) = ( k_k ⊕ k_{k+1} ,  k ⊕ (k+1) )    lexicographic
/// ```
#[inline(always)]
pub(crate) fn dist<K: RadixKey>(keys: &[K], k: usize) -> (u64, u32) {
    let x = keys[k].widen() ^ keys[k + 1].widen();
    (x, (k as u32) ^ (k as u32 + 1))
}

/// Build topology and finished slots in one bottom-up pass over `keys` (sorted ascending, 1 to
/// `u32::MAX` keys); `sorted[p]` is the box of the primitive at sorted position `p`.
///
/// Each leaf climbs while it is the second to reach a node: it records itself as the node's
/// left or right child, then swaps its own range end into the node's `other` slot (`AcqRel`).
/// The first arrival reads 0 (empty) and stops; the second reads the first's range end, extends
/// its range, and — the acquire half having made the first child's slot visible — finishes the
/// node and climbs on.
pub fn build_apetrei<K: RadixKey>(keys: &[K], sorted: &[Aabb], k: &CollapseParams) -> RadixTree {
    let n = keys.len().max(1);
    let mut tree = RadixTree::with_leaves(n, false);
    if keys.len() < 2 {
        return tree;
    }
    // Range ends are stored plus one, so that the zeroed buffer means "nobody arrived yet".
    let other: Vec<AtomicU32> = zeroed(n - 1);
    let root = AtomicU32::new(NONE);
    let leaf0 = (n - 1) as u32;
    {
        let tree = &tree;
        (0..n)
            .into_par_iter()
            .with_min_len(LEAVES_PER_TASK)
            .for_each(|p| {
                let (mut lo, mut hi) = (p, p);
                let mut cur = leaf0 + p as u32;
                loop {
                    if lo == 0 && hi == n - 1 {
                        root.store(cur, Ordering::Relaxed);
                        break;
                    }
                    let go_right_parent =
                        lo == 0 || (hi != n - 1 && dist(keys, hi) < dist(keys, lo - 1));
                    let parent;
                    if go_right_parent {
                        parent = hi;
                        tree.children[parent][0].store(cur, Ordering::Relaxed);
                        let prev = other[parent].swap(lo as u32 + 1, Ordering::AcqRel);
                        if prev == 0 {
                            break;
                        }
                        hi = prev as usize - 1;
                    } else {
                        parent = lo - 1;
                        tree.children[parent][1].store(cur, Ordering::Relaxed);
                        let prev = other[parent].swap(hi as u32 + 1, Ordering::AcqRel);
                        if prev == 0 {
                            break;
                        }
                        lo = prev as usize - 1;
                    }
                    let (l, r) = tree.children_of(parent as u32);
                    tree.finish(parent as u32, l, r, sorted, k);
                    cur = parent as u32;
                }
            });
    }
    tree.root = root.into_inner();
    tree
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn paper_example() {
        let keys: [u32; 8] = [
            0b00001, 0b00010, 0b00100, 0b00101, 0b10011, 0b11000, 0b11001, 0b11110,
        ];
        let boxes: Vec<Aabb> = (0..8).map(|i| Aabb::point(Vec3::splat(i as f32))).collect();
        let t = build_apetrei(&keys, &boxes, &CollapseParams::NONE);
        let l = |p: u32| 7 + p;
        assert_eq!(t.root, 3);
        assert_eq!(t.children_of(1), (0, 2));
        assert_eq!(t.children_of(0), (l(0), l(1)));
        assert_eq!(t.children_of(2), (l(2), l(3)));
        assert_eq!(t.children_of(3), (1, 4));
        assert_eq!(t.children_of(4), (l(4), 6));
        assert_eq!(t.children_of(6), (5, l(7)));
        assert_eq!(t.children_of(5), (l(5), l(6)));
        let s = t.slots[3].load();
        assert_eq!((s.first, s.count), (0, 8));
        assert_eq!(s.bounds, Aabb::new(Vec3::ZERO, Vec3::splat(7.0)));
    }
}
