//! Per-byte lookup tables, built once per layout: any pattern, branch-free, one load per byte
//! of each channel value. The fastest general expander on CPUs where `pdep` is microcoded.
//!
//! For channel `c` and byte `j` of its value, `T[c,j][v]` is the code with only the bits of
//! `v << 8j` of channel `c` in place. A 20/19/19/6 layout uses 3+3+3+1 = 10 tables (20 KiB).
//!
//! ```text
//!   q_x = 0b1011_0110_0101_1100_1010       (20 bits: bytes 2, 1, 0)
//!   code = T[x,0][0xCA] | T[x,1][0x65] | T[x,2][0x0B] | T[y,0][..] | … | T[s,0][q_s]
//! ```
//!
//! The decoder uses one table per code byte: a code byte holds consecutive bits of each channel,
//! so `D[j][b]` packs the four channel fragments (one byte each) and a per-(byte, channel)
//! shift puts each fragment back in place (8 KiB).
#![forbid(unsafe_code)]

use super::low_mask;
use crate::layout::{Channel, Layout};

use super::reference::Reference;

/// Largest number of (channel, byte) tables a layout can need: ⌈b/8⌉ summed over four channels
/// whose bits add up to at most 64.
pub const MAX_TABLES: usize = 12;

/// The table expander of one layout.
#[derive(Clone)]
pub struct Table {
    /// `(channel index, byte index)` of each table, in use order.
    slots: [(u8, u8); MAX_TABLES],
    ntables: usize,
    enc: [[u64; 256]; MAX_TABLES],
    /// `dec[j][b]`: channel fragments (byte per channel) of code byte `j` holding `b`.
    dec: [[u32; 256]; 8],
    /// `shift[j][c]`: where the fragment of channel `c` from code byte `j` goes in its value.
    shift: [[u8; 4]; 8],
    nbytes: usize,
}

impl core::fmt::Debug for Table {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "Table({} tables)", self.ntables)
    }
}

impl Table {
    /// Build the tables for a layout (always available).
    pub fn new(layout: &Layout) -> Table {
        let r = Reference::new(layout);
        let mut t = Table {
            slots: [(0, 0); MAX_TABLES],
            ntables: 0,
            enc: [[0; 256]; MAX_TABLES],
            dec: [[0; 256]; 8],
            shift: [[0; 4]; 8],
            nbytes: (layout.len() as usize).div_ceil(8),
        };
        for c in Channel::ALL {
            let bits = layout.bits(c);
            for j in 0..bits.div_ceil(8) {
                let slot = t.ntables;
                t.slots[slot] = (c.index() as u8, j as u8);
                for v in 0..256u64 {
                    let mut q = [0u64; 4];
                    q[c.index()] = v << (8 * j);
                    t.enc[slot][v as usize] = r.expand(q);
                }
                t.ntables += 1;
            }
        }
        // Decoder: for each code byte, find each channel's lowest value-bit in it (the shift),
        // then tabulate the fragments with the reference decoder.
        for j in 0..t.nbytes {
            let mut lowest = [u32::MAX; 4];
            for bit in 0..8 {
                let code_bit = 8 * j as u32 + bit;
                if code_bit >= layout.len() {
                    break;
                }
                let q = r.compact(1u64 << code_bit);
                for c in 0..4 {
                    if q[c] != 0 {
                        lowest[c] = lowest[c].min(q[c].trailing_zeros());
                    }
                }
            }
            for (sh, &low) in t.shift[j].iter_mut().zip(&lowest) {
                *sh = if low == u32::MAX { 0 } else { low as u8 };
            }
            for b in 0..256u64 {
                let code = (b << (8 * j)) & low_mask(layout.len());
                let q = r.compact(code);
                let mut packed = 0u32;
                for (c, (&qc, &sh)) in q.iter().zip(&t.shift[j]).enumerate() {
                    packed |= ((qc >> sh) as u32 & 0xff) << (8 * c);
                }
                t.dec[j][b as usize] = packed;
            }
        }
        t
    }

    /// `(channel index, byte index)` of each encoding table, in the order of [`Table::entries`].
    #[inline]
    pub fn slots(&self) -> &[(u8, u8)] {
        &self.slots[..self.ntables]
    }

    /// The encoding tables: `entries()[i][v]` is the code bits of byte value `v` in slot `i`.
    #[inline]
    pub fn entries(&self) -> &[[u64; 256]] {
        &self.enc[..self.ntables]
    }

    /// Interleave channel values (x, y, z, s); bits above each channel's width are ignored.
    #[inline]
    pub fn expand(&self, q: [u64; 4]) -> u64 {
        let mut code = 0u64;
        for i in 0..self.ntables {
            let (c, j) = self.slots[i];
            let byte = (q[c as usize] >> (8 * j as u32)) as u8;
            code |= self.enc[i][byte as usize];
        }
        // Entries were made by the reference, which ignores value bits above a channel's
        // width, so no mask is needed here.
        code
    }

    /// Split a code back into channel values (bits above the layout width are ignored).
    #[inline]
    pub fn compact(&self, code: u64) -> [u64; 4] {
        let mut q = [0u64; 4];
        for j in 0..self.nbytes {
            let e = self.dec[j][((code >> (8 * j)) & 0xff) as usize];
            for (c, qc) in q.iter_mut().enumerate() {
                *qc |= (((e >> (8 * c)) & 0xff) as u64) << self.shift[j][c];
            }
        }
        q
    }
}
