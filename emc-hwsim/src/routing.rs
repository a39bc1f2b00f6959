//! The interleave: from the packed word of quantised channel fields to the code word.
//! Fixed layouts (Morton) are plain wires; programmable ones use a Beneš network (default) or a
//! full crossbar, whose control bits are computed once per frame from the layout pattern.
//!
//! The packed word puts each channel's value in a contiguous field, size lowest:
//!
//! ```text
//!   bit  len-1 ..                                              .. 0
//!        [ x : nx bits ][ y : ny bits ][ z : nz bits ][ s : ns bits ]   (bits >= len are 0)
//! ```
//!
//! and the network moves packed bit `src[j]` to code bit `j`. Code position `k` (MSB first) is
//! code bit `len − 1 − k`; the `r`-th occurrence of channel `c` in the pattern takes the field
//! bit `offset[c] + n_c − 1 − r` (channel values are written MSB first, as in the pattern).
#![forbid(unsafe_code)]

use emc_core::Layout;

/// A permutation of the 64 bit lanes: `src[j]` is the packed bit that feeds code bit `j`.
pub type Permutation = [u8; 64];

/// Field offsets of the packed word (x, y, z, s) for a layout: `s` at 0, then `z`, `y`, `x`.
pub fn field_offsets(bits: [u32; 4]) -> [u32; 4] {
    let s = 0;
    let z = bits[3];
    let y = z + bits[2];
    let x = y + bits[1];
    [x, y, z, s]
}

/// The bit permutation a layout asks of the network (identity above the code length).
pub fn layout_permutation(layout: &Layout) -> Permutation {
    let bits = layout.bit_counts();
    let off = field_offsets(bits);
    let len = layout.len() as usize;
    let mut seen = [0u32; 4];
    let mut src = [0u8; 64];
    for (j, s) in src.iter_mut().enumerate() {
        *s = j as u8;
    }
    for (k, c) in layout.channels().iter().enumerate() {
        let ci = c.index();
        let r = seen[ci];
        seen[ci] += 1;
        src[len - 1 - k] = (off[ci] + bits[ci] - 1 - r) as u8;
    }
    src
}

/// Apply a permutation as wires: code bit `j < len` is packed bit `src[j]`.
#[inline]
pub fn permute(src: &Permutation, packed: u64, len: u32) -> u64 {
    let mut code = 0u64;
    for (j, &s) in src.iter().enumerate().take(len as usize) {
        code |= ((packed >> s) & 1) << j;
    }
    code
}

/// A Beneš network on `2^k` bit lanes: `2k − 1` columns of `2^(k−1)` 2×2 switches, column `i`
/// exchanging lanes `d` apart with `d = 2^(k−1−min(i, 2k−2−i))` (32, 16, …, 1, …, 16, 32 for
/// 64 lanes). One control bit per switch, stored per column as a mask of the lower lane.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Benes {
    k: u32,
    masks: Vec<u64>,
}

impl Benes {
    /// Route a permutation of `2^k` lanes (`k` in 1..=6) by the looping algorithm; `src[j]`
    /// for `j < 2^k` must be a permutation of `0..2^k`.
    pub fn route(src: &[u8], k: u32) -> Benes {
        assert!((1..=6).contains(&k), "Beneš size 2^{k} out of range");
        let n = 1usize << k;
        let s: Vec<usize> = src[..n].iter().map(|&v| v as usize).collect();
        let mut masks = vec![0u64; 2 * k as usize - 1];
        route_rec(&s, 0, 0, k as usize, &mut masks);
        Benes { k, masks }
    }

    /// Number of columns (`2k − 1`).
    pub fn columns(&self) -> usize {
        self.masks.len()
    }

    /// Switches per column (`2^(k−1)`).
    pub fn switches_per_column(&self) -> usize {
        1 << (self.k - 1)
    }

    /// Lanes (`2^k`).
    pub fn lanes(&self) -> u32 {
        1 << self.k
    }

    /// Control bits (one per switch).
    pub fn control_bits(&self) -> usize {
        self.columns() * self.switches_per_column()
    }

    /// Control masks per column.
    pub fn masks(&self) -> &[u64] {
        &self.masks
    }

    /// Exchange distance of column `i`.
    #[inline(always)]
    pub fn distance(&self, i: usize) -> u32 {
        let last = 2 * self.k as usize - 2;
        1 << (self.k as usize - 1 - i.min(last - i))
    }

    /// Pass a word through columns `range` (the unit splits the network over pipeline cycles).
    #[inline(always)]
    pub fn apply_columns(&self, mut x: u64, range: core::ops::Range<usize>) -> u64 {
        for i in range {
            let d = self.distance(i);
            // 2×2 switch on lanes (p, p + d) for every set bit p of the mask: exchange when set.
            let t = ((x >> d) ^ x) & self.masks[i];
            x ^= t | (t << d);
        }
        x
    }

    /// Pass a word through the whole network.
    #[inline(always)]
    pub fn apply(&self, x: u64) -> u64 {
        self.apply_columns(x, 0..self.masks.len())
    }
}

/// One level of the looping algorithm on the block of lanes `base .. base + src.len()`.
fn route_rec(src: &[usize], base: usize, depth: usize, k: usize, masks: &mut [u64]) {
    let m = src.len();
    let first = depth;
    let last = 2 * k - 2 - depth;
    if m == 2 {
        if src[0] == 1 {
            masks[first] |= 1 << base;
        }
        return;
    }
    let half = m / 2;
    let mut inv = vec![0usize; m];
    for (j, &i) in src.iter().enumerate() {
        inv[i] = j;
    }
    // 0 = through the lower sub-network, 1 = through the upper one; 2 = not decided yet.
    let mut in_sub = vec![2u8; m];
    let mut out_sub = vec![2u8; m];
    for start in 0..half {
        if out_sub[start] != 2 {
            continue;
        }
        let mut j = start;
        loop {
            // Output j is fed by the lower network, hence so is its source input; that input's
            // switch partner must take the upper network, and so must the output it feeds.
            out_sub[j] = 0;
            let i = src[j];
            in_sub[i] = 0;
            let i2 = i ^ half;
            in_sub[i2] = 1;
            let j2 = inv[i2];
            out_sub[j2] = 1;
            let j3 = j2 ^ half;
            if out_sub[j3] != 2 {
                break;
            }
            j = j3;
        }
    }
    let mut lower = vec![0usize; half];
    let mut upper = vec![0usize; half];
    for sw in 0..half {
        if in_sub[sw] == 1 {
            masks[first] |= 1 << (base + sw);
        }
        if out_sub[sw] == 1 {
            masks[last] |= 1 << (base + sw);
        }
        let (jl, ju) = if out_sub[sw] == 0 {
            (sw, sw + half)
        } else {
            (sw + half, sw)
        };
        lower[sw] = src[jl] & (half - 1);
        upper[sw] = src[ju] & (half - 1);
    }
    route_rec(&lower, base, depth + 1, k, masks);
    route_rec(&upper, base + half, depth + 1, k, masks);
}

/// Fixed Morton wiring `(x y z)^n`, x most significant, for `n <= 21`: no logic at all in the
/// unit. The model evaluates the wires with shift-and-mask spreads (each channel's bit `i`
/// moves to bit `3i`), then offsets x by 2 and y by 1.
#[inline(always)]
pub fn morton_wires(x: u64, y: u64, z: u64) -> u64 {
    (spread3(x) << 2) | (spread3(y) << 1) | spread3(z)
}

/// Bit `i` of `v` (`i < 21`) to bit `3i`.
#[inline(always)]
fn spread3(v: u64) -> u64 {
    // 21 bits: split into groups that double in spacing at each step.
    let mut x = v & 0x1f_ffff;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

/// A full crossbar: one `log2(lanes)`-bit select per code bit.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Crossbar {
    sel: Vec<u8>,
}

impl Crossbar {
    /// Selects for the first `lanes` code bits of a permutation.
    pub fn new(src: &Permutation, lanes: u32) -> Crossbar {
        Crossbar {
            sel: src[..lanes as usize].to_vec(),
        }
    }

    /// Code bit `j` takes packed bit `sel[j]`.
    #[inline]
    pub fn apply(&self, packed: u64) -> u64 {
        let mut code = 0u64;
        for (j, &s) in self.sel.iter().enumerate() {
            code |= ((packed >> s) & 1) << j;
        }
        code
    }

    /// The selects: code bit `j` takes packed bit `selects()[j]`.
    pub fn selects(&self) -> &[u8] {
        &self.sel
    }

    /// Output bits (select registers).
    pub fn lanes(&self) -> u32 {
        self.sel.len() as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn permute_ref(src: &[u8], x: u64) -> u64 {
        let mut y = 0;
        for (j, &s) in src.iter().enumerate() {
            y |= ((x >> s) & 1) << j;
        }
        y
    }

    #[test]
    fn spread3_moves_bit_i_to_3i() {
        for i in 0..21 {
            assert_eq!(spread3(1 << i), 1 << (3 * i));
        }
        assert_eq!(spread3(1 << 21), 0);
    }

    #[test]
    fn benes_realises_permutations() {
        let mut state = 0x1234_5678_9abc_def0u64;
        let mut rnd = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for k in 1..=6u32 {
            let n = 1usize << k;
            for _ in 0..200 {
                let mut p: Vec<u8> = (0..n as u8).collect();
                for i in (1..n).rev() {
                    let j = (rnd() % (i as u64 + 1)) as usize;
                    p.swap(i, j);
                }
                let net = Benes::route(&p, k);
                assert_eq!(net.control_bits(), (2 * k as usize - 1) * (n / 2));
                for _ in 0..8 {
                    let mask = if n == 64 { u64::MAX } else { (1u64 << n) - 1 };
                    let x = rnd() & mask;
                    assert_eq!(net.apply(x), permute_ref(&p, x), "k={k} p={p:?}");
                }
                for (b, &pb) in p.iter().enumerate() {
                    assert_eq!(net.apply(1 << pb), 1 << b);
                }
            }
        }
    }
}
