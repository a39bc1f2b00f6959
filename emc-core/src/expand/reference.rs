//! The bit-loop reference: one position at a time, MSB first, exactly as the layout reads.
//! It is the oracle every other backend is tested against; it is not meant to be fast.
#![forbid(unsafe_code)]

use crate::layout::Layout;

/// The reference expander of one layout.
#[derive(Clone, Debug)]
pub struct Reference {
    layout: Layout,
}

impl Reference {
    /// Build for a layout (always available).
    pub fn new(layout: &Layout) -> Reference {
        Reference { layout: *layout }
    }

    /// Interleave channel values (x, y, z, s) into a right-aligned code. Each channel value is
    /// read from its `bits` low bits; higher bits are ignored.
    pub fn expand(&self, q: [u64; 4]) -> u64 {
        let mut remaining = self.layout.bit_counts();
        let mut code = 0u64;
        for &c in self.layout.channels() {
            let i = c.index();
            remaining[i] -= 1;
            code = (code << 1) | ((q[i] >> remaining[i]) & 1);
        }
        code
    }

    /// Split a code back into its channel values (bits above the layout width are ignored).
    pub fn compact(&self, code: u64) -> [u64; 4] {
        let mut q = [0u64; 4];
        let n = self.layout.len();
        for (k, &c) in self.layout.channels().iter().enumerate() {
            let bit = (code >> (n - 1 - k as u32)) & 1;
            q[c.index()] = (q[c.index()] << 1) | bit;
        }
        q
    }
}
