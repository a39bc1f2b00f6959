//! Shift-and-mask ("magic bits") expansion for regular patterns: a repeated permutation of `k`
//! distinct channels (`k` = 1..=4) with the same bit count each, such as `morton30`,
//! `morton63` (`(xyz)^21`) and `emc64-sort` (`(a0 a1 a2 s)^16`). No tables, no branches.
#![forbid(unsafe_code)]

use super::low_mask;
use crate::layout::Layout;

/// The magic-bits expander of one regular layout.
#[derive(Clone, Copy, Debug)]
pub struct Magic {
    /// Number of interleaved channels (the period).
    k: u32,
    /// For each channel (x, y, z, s): its shift inside a period (k − 1 for the first of the
    /// period, 0 for the last), or `u32::MAX` when unused.
    shift: [u32; 4],
    /// Bits per channel.
    n: u32,
}

impl Magic {
    /// Build for a layout, or `None` when its pattern is not regular or too wide for the
    /// spreads (k = 2: 32 bits, k = 3: 21, k = 4: 16 per channel).
    pub fn new(layout: &Layout) -> Option<Magic> {
        let ch = layout.channels();
        let mut k = 0usize;
        let mut seen = [false; 4];
        while k < ch.len() && !seen[ch[k].index()] {
            seen[ch[k].index()] = true;
            k += 1;
        }
        if !ch.len().is_multiple_of(k) || (0..ch.len()).any(|i| ch[i] != ch[i % k]) {
            return None;
        }
        let n = (ch.len() / k) as u32;
        let fits = match k {
            1 => n <= 64,
            2 => n <= 32,
            3 => n <= 21,
            _ => n <= 16,
        };
        if !fits {
            return None;
        }
        let mut shift = [u32::MAX; 4];
        for (p, c) in ch[..k].iter().enumerate() {
            shift[c.index()] = (k - 1 - p) as u32;
        }
        Some(Magic {
            k: k as u32,
            shift,
            n,
        })
    }

    /// The period: number of interleaved channels (1..=4).
    #[inline]
    pub fn period(&self) -> u32 {
        self.k
    }

    /// Bits per channel.
    #[inline]
    pub fn bits_per_channel(&self) -> u32 {
        self.n
    }

    /// Per channel (x, y, z, s): the left shift of its spread inside a period, `None` when the
    /// channel is not used.
    #[inline]
    pub fn shifts(&self) -> [Option<u32>; 4] {
        self.shift
            .map(|s| if s == u32::MAX { None } else { Some(s) })
    }

    /// Interleave channel values (x, y, z, s); bits above each channel's width are ignored.
    #[inline]
    pub fn expand(&self, q: [u64; 4]) -> u64 {
        let m = low_mask(self.n);
        let mut code = 0u64;
        for (c, &qc) in q.iter().enumerate() {
            let s = self.shift[c];
            // Unused channels have shift u32::MAX; `wrapping` keeps the path branch-free and the
            // `used` mask zeroes their contribution.
            let used = 0u64.wrapping_sub((s != u32::MAX) as u64);
            let spread = match self.k {
                1 => qc & m,
                2 => spread2(qc & m),
                3 => spread3(qc & m),
                _ => spread4(qc & m),
            };
            code |= (spread << (s & 3)) & used;
        }
        code
    }

    /// Split a code back into channel values (bits above the layout width are ignored).
    #[inline]
    pub fn compact(&self, code: u64) -> [u64; 4] {
        let mut q = [0u64; 4];
        for (c, qc) in q.iter_mut().enumerate() {
            let s = self.shift[c];
            if s == u32::MAX {
                continue;
            }
            let v = code >> s;
            // The gathers take every k-th bit of the whole word; masking to the channel width
            // drops code bits above the layout width, as every other decoder does.
            *qc = match self.k {
                1 => v,
                2 => compact2(v),
                3 => compact3(v),
                _ => compact4(v),
            } & low_mask(self.n);
        }
        q
    }
}

/// Insert one zero above every bit of a 32-bit value.
///
/// ```text
///   ---- ---- ---- ---- fedc ba98 7654 3210   (16 of the 32 bits shown)
///   ---- ---- fedc ba98 ---- ---- 7654 3210   << 8,  & 0x00FF00FF…
///   ---- fedc ---- ba98 ---- 7654 ---- 3210   << 4,  & 0x0F0F0F0F…
///   --fe --dc --ba --98 --76 --54 --32 --10   << 2,  & 0x33333333…
///   -f-e -d-c -b-a -9-8 -7-6 -5-4 -3-2 -1-0   << 1,  & 0x55555555…
/// ```
#[inline(always)]
pub fn spread2(v: u64) -> u64 {
    let mut x = v & 0xFFFF_FFFF;
    x = (x | (x << 16)) & 0x0000_FFFF_0000_FFFF;
    x = (x | (x << 8)) & 0x00FF_00FF_00FF_00FF;
    x = (x | (x << 4)) & 0x0F0F_0F0F_0F0F_0F0F;
    x = (x | (x << 2)) & 0x3333_3333_3333_3333;
    x = (x | (x << 1)) & 0x5555_5555_5555_5555;
    x
}

/// Inverse of [`spread2`]: gather every other bit.
#[inline(always)]
pub fn compact2(v: u64) -> u64 {
    let mut x = v & 0x5555_5555_5555_5555;
    x = (x | (x >> 1)) & 0x3333_3333_3333_3333;
    x = (x | (x >> 2)) & 0x0F0F_0F0F_0F0F_0F0F;
    x = (x | (x >> 4)) & 0x00FF_00FF_00FF_00FF;
    x = (x | (x >> 8)) & 0x0000_FFFF_0000_FFFF;
    x = (x | (x >> 16)) & 0x0000_0000_FFFF_FFFF;
    x
}

/// Insert two zeros above every bit of a 21-bit value (the Morton-63 spread).
///
/// ```text
///   value bits k (0..21) move to bit 3k:
///   (x | x<<32) & 0x001F00000000FFFF    bits 16..20 to 48..52
///   (x | x<<16) & 0x001F0000FF0000FF    bytes 16 apart
///   (x | x<<8)  & 0x100F00F00F00F00F    nibbles 8 apart
///   (x | x<<4)  & 0x10C30C30C30C30C3    pairs 4 apart
///   (x | x<<2)  & 0x1249249249249249    bits 3 apart
/// ```
#[inline(always)]
pub fn spread3(v: u64) -> u64 {
    let mut x = v & 0x1F_FFFF;
    x = (x | (x << 32)) & 0x001F_0000_0000_FFFF;
    x = (x | (x << 16)) & 0x001F_0000_FF00_00FF;
    x = (x | (x << 8)) & 0x100F_00F0_0F00_F00F;
    x = (x | (x << 4)) & 0x10C3_0C30_C30C_30C3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

/// Inverse of [`spread3`]: gather every third bit.
#[inline(always)]
pub fn compact3(v: u64) -> u64 {
    let mut x = v & 0x1249_2492_4924_9249;
    x = (x | (x >> 2)) & 0x10C3_0C30_C30C_30C3;
    x = (x | (x >> 4)) & 0x100F_00F0_0F00_F00F;
    x = (x | (x >> 8)) & 0x001F_0000_FF00_00FF;
    x = (x | (x >> 16)) & 0x001F_0000_0000_FFFF;
    x = (x | (x >> 32)) & 0x1F_FFFF;
    x
}

/// Insert three zeros above every bit of a 16-bit value (the 4-D spread of `emc64-sort`).
///
/// ```text
///   ---- ---- ---- ---- fedc ba98 7654 3210   (x, 16 bits)
///   (x | x<<24) & 0x000000FF000000FF        byte 1 to bits 32..39
///   (x | x<<12) & 0x000F000F000F000F        nibbles 16 apart
///   (x | x<<6)  & 0x0303030303030303        pairs 8 apart
///   (x | x<<3)  & 0x1111111111111111        bits 4 apart
/// ```
#[inline(always)]
pub fn spread4(v: u64) -> u64 {
    let mut x = v & 0xFFFF;
    x = (x | (x << 24)) & 0x0000_00FF_0000_00FF;
    x = (x | (x << 12)) & 0x000F_000F_000F_000F;
    x = (x | (x << 6)) & 0x0303_0303_0303_0303;
    x = (x | (x << 3)) & 0x1111_1111_1111_1111;
    x
}

/// Inverse of [`spread4`]: gather every fourth bit.
#[inline(always)]
pub fn compact4(v: u64) -> u64 {
    let mut x = v & 0x1111_1111_1111_1111;
    x = (x | (x >> 3)) & 0x0303_0303_0303_0303;
    x = (x | (x >> 6)) & 0x000F_000F_000F_000F;
    x = (x | (x >> 12)) & 0x0000_00FF_0000_00FF;
    x = (x | (x >> 24)) & 0xFFFF;
    x
}
