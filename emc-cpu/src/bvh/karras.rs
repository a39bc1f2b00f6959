//! Karras 2012: the binary radix tree over sorted codes, one independent task per internal node
//! (step 4 of the LBVH pipeline, builder `lbvh`). Equal codes are extended by their sorted
//! position, so every input gives one well-defined tree. Bounds come after, from `refit`.
#![forbid(unsafe_code)]

use std::sync::atomic::Ordering;

use rayon::prelude::*;

use super::refit::RadixTree;
use crate::sort::RadixKey;

/// Internal nodes handled per rayon task.
const NODES_PER_TASK: usize = 4096;

/// Common-prefix length of the index-augmented keys at sorted positions `i` and `j`, or −1 when
/// `j` is outside `0..n`. Every key is read as a 64-bit word (`B = 64` for `u32` keys too: their
/// 32 extra leading zeros shift every unequal-key value by the same amount, which changes no
/// comparison), and equal keys continue with the 32-bit positions:
///
/// ```text
/// δ(i, j) = clz64(k_i ⊕ k_j)          if k_i ≠ k_j
///         = 64 + clz32(i ⊕ j)          if k_i = k_j
/// ```
#[inline(always)]
pub fn delta<K: RadixKey>(keys: &[K], i: usize, j: i64) -> i32 {
    if j < 0 || j as usize >= keys.len() {
        return -1;
    }
    let j = j as usize;
    let x = keys[i].widen() ^ keys[j].widen();
    if x != 0 {
        x.leading_zeros() as i32
    } else {
        64 + ((i as u32) ^ (j as u32)).leading_zeros() as i32
    }
}

/// Children of internal node `i` (node ids: internal `0..n−1`, leaf `p` = `n − 1 + p`) and the
/// range `[first, last]` of sorted positions it covers.
#[inline]
pub fn node_children<K: RadixKey>(keys: &[K], i: usize) -> ([u32; 2], [u32; 2]) {
    let n = keys.len();
    let ii = i as i64;
    let d: i64 = if delta(keys, i, ii + 1) > delta(keys, i, ii - 1) {
        1
    } else {
        -1
    };
    let dmin = delta(keys, i, ii - d);
    let mut lmax: i64 = 2;
    while delta(keys, i, ii + lmax * d) > dmin {
        lmax *= 2;
    }
    let mut l: i64 = 0;
    let mut t = lmax / 2;
    while t >= 1 {
        if delta(keys, i, ii + (l + t) * d) > dmin {
            l += t;
        }
        t /= 2;
    }
    let j = ii + l * d;
    let dnode = delta(keys, i, j);
    let mut s: i64 = 0;
    let mut t = l;
    loop {
        t = (t + 1) / 2;
        if delta(keys, i, ii + (s + t) * d) > dnode {
            s += t;
        }
        if t == 1 {
            break;
        }
    }
    let gamma = ii + s * d + d.min(0);
    let (lo, hi) = (ii.min(j), ii.max(j));
    let leaf0 = (n - 1) as i64;
    let left = if lo == gamma { leaf0 + gamma } else { gamma };
    let right = if hi == gamma + 1 {
        leaf0 + gamma + 1
    } else {
        gamma + 1
    };
    ([left as u32, right as u32], [lo as u32, hi as u32])
}

/// Build the topology (children and parent links) over `keys`, which must be sorted ascending
/// and hold between 1 and `u32::MAX` keys (the pipeline driver checks both). The root is node 0.
pub fn build_karras<K: RadixKey>(keys: &[K]) -> RadixTree {
    let n = keys.len().max(1);
    let tree = RadixTree::with_leaves(n, true);
    if keys.len() < 2 {
        return tree;
    }
    tree.children
        .par_iter()
        .enumerate()
        .with_min_len(NODES_PER_TASK)
        .for_each(|(i, slot)| {
            let (c, _) = node_children(keys, i);
            slot[0].store(c[0], Ordering::Relaxed);
            slot[1].store(c[1], Ordering::Relaxed);
            tree.parents[c[0] as usize].store(i as u32, Ordering::Relaxed);
            tree.parents[c[1] as usize].store(i as u32, Ordering::Relaxed);
        });
    tree
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 8-key example of Karras' paper (5-bit keys).
    #[test]
    fn paper_example() {
        let keys: [u32; 8] = [
            0b00001, 0b00010, 0b00100, 0b00101, 0b10011, 0b11000, 0b11001, 0b11110,
        ];
        let t = build_karras(&keys);
        let l = |p: u32| 7 + p;
        let want = [
            [3, 4],
            [l(0), l(1)],
            [l(2), l(3)],
            [1, 2],
            [l(4), 5],
            [6, l(7)],
            [l(5), l(6)],
        ];
        for (i, w) in want.iter().enumerate() {
            let (a, b) = t.children_of(i as u32);
            assert_eq!([a, b], *w, "node {i}");
        }
        let ranges = [[0, 7], [0, 1], [2, 3], [0, 3], [4, 7], [5, 7], [5, 6]];
        for (i, r) in ranges.iter().enumerate() {
            assert_eq!(node_children(&keys, i).1, *r, "range of node {i}");
        }
        assert_eq!(t.root, 0);
        assert_eq!(
            t.parents[0].load(Ordering::Relaxed),
            super::super::refit::NONE
        );
    }
}
