//! Bit expansion backends: one module each, the same two methods (`expand`, `compact`).
//! [`Expander`] holds whichever one dispatch picked for an encoder, decided once.
//!
//! | backend | patterns | cost on a microcoded-pdep CPU (Zen 1) |
//! |---|---|---|
//! | [`mod@reference`] | any | a bit loop: the oracle |
//! | [`magic`] | regular (`(xyz)^n`, `(a0 a1 a2 s)^16`, …) | shifts and masks |
//! | [`table`] | any | one load per byte of each channel |
//! | `pdep` (x86_64) | any | one instruction per channel where pdep is fast |

use core::fmt;
use core::str::FromStr;

use crate::error::Error;
use crate::layout::Layout;

pub mod magic;
#[cfg(target_arch = "x86_64")]
pub mod pdep;
pub mod reference;
pub mod table;

/// The low `n` bits set (`n` up to 64): the range mask of an `n`-bit channel value.
#[inline]
pub(crate) fn low_mask(n: u32) -> u64 {
    if n >= 64 {
        u64::MAX
    } else {
        (1u64 << n) - 1
    }
}

/// Names of the expansion backends (CLI, CSV and docs use the lower-case names).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Backend {
    /// The bit loop (oracle).
    Reference,
    /// Shift/mask spreads for regular patterns.
    Magic,
    /// Per-byte tables for any pattern.
    Table,
    /// BMI2 `pdep`/`pext` (x86_64).
    Pdep,
}

impl Backend {
    /// All backends, in the order tables list them.
    pub const ALL: [Backend; 4] = [
        Backend::Reference,
        Backend::Magic,
        Backend::Table,
        Backend::Pdep,
    ];

    /// The lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Reference => "reference",
            Backend::Magic => "magic",
            Backend::Table => "table",
            Backend::Pdep => "pdep",
        }
    }
}

impl fmt::Display for Backend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Backend {
    type Err = Error;
    /// Parse a lower-case backend name; [`Error::UnknownBackend`] for anything else.
    fn from_str(s: &str) -> Result<Self, Error> {
        Backend::ALL
            .into_iter()
            .find(|b| b.name() == s)
            .ok_or(Error::UnknownBackend)
    }
}

/// One built backend.
// The table variant holds its tables inline (about 32 KiB): emc-core has no allocator to box
// them, and an expander is built once per encoder, so the size costs nothing per code.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum Expander {
    /// See [`reference::Reference`].
    Reference(reference::Reference),
    /// See [`magic::Magic`].
    Magic(magic::Magic),
    /// See [`table::Table`].
    Table(table::Table),
    /// See [`pdep::Pdep`].
    #[cfg(target_arch = "x86_64")]
    Pdep(pdep::Pdep),
}

impl Expander {
    /// Build a named backend for a layout, or `None` when it cannot serve it here (magic on an
    /// irregular pattern, pdep without BMI2 or off x86_64).
    pub fn new(backend: Backend, layout: &Layout) -> Option<Expander> {
        match backend {
            Backend::Reference => Some(Expander::Reference(reference::Reference::new(layout))),
            Backend::Magic => magic::Magic::new(layout).map(Expander::Magic),
            Backend::Table => Some(Expander::Table(table::Table::new(layout))),
            #[cfg(target_arch = "x86_64")]
            Backend::Pdep => pdep::Pdep::new(layout).map(Expander::Pdep),
            #[cfg(not(target_arch = "x86_64"))]
            Backend::Pdep => None,
        }
    }

    /// Which backend this is.
    pub fn backend(&self) -> Backend {
        match self {
            Expander::Reference(_) => Backend::Reference,
            Expander::Magic(_) => Backend::Magic,
            Expander::Table(_) => Backend::Table,
            #[cfg(target_arch = "x86_64")]
            Expander::Pdep(_) => Backend::Pdep,
        }
    }

    /// Interleave channel values (x, y, z, s) into a right-aligned code.
    #[inline]
    pub fn expand(&self, q: [u64; 4]) -> u64 {
        match self {
            Expander::Reference(e) => e.expand(q),
            Expander::Magic(e) => e.expand(q),
            Expander::Table(e) => e.expand(q),
            #[cfg(target_arch = "x86_64")]
            Expander::Pdep(e) => e.expand(q),
        }
    }

    /// Split a code into channel values.
    #[inline]
    pub fn compact(&self, code: u64) -> [u64; 4] {
        match self {
            Expander::Reference(e) => e.compact(code),
            Expander::Magic(e) => e.compact(code),
            Expander::Table(e) => e.compact(code),
            #[cfg(target_arch = "x86_64")]
            Expander::Pdep(e) => e.compact(code),
        }
    }

    /// [`Expander::expand`] of every element of `q` into `out` (pairs up to the shorter of
    /// the two): the backend is chosen once for the slice and its loop runs inside it (for
    /// `pdep`, inside the BMI2 function, where the instructions inline).
    pub fn expand_slice(&self, q: &[[u64; 4]], out: &mut [u64]) {
        match self {
            Expander::Reference(e) => each(q, out, |v| e.expand(v)),
            Expander::Magic(e) => each(q, out, |v| e.expand(v)),
            Expander::Table(e) => each(q, out, |v| e.expand(v)),
            #[cfg(target_arch = "x86_64")]
            Expander::Pdep(e) => e.expand_slice(q, out),
        }
    }

    /// [`Expander::compact`] of every code of `codes` into `out` (pairs up to the shorter of
    /// the two), the backend chosen once for the slice as in [`Expander::expand_slice`].
    pub fn compact_slice(&self, codes: &[u64], out: &mut [[u64; 4]]) {
        match self {
            Expander::Reference(e) => each(codes, out, |c| e.compact(c)),
            Expander::Magic(e) => each(codes, out, |c| e.compact(c)),
            Expander::Table(e) => each(codes, out, |c| e.compact(c)),
            #[cfg(target_arch = "x86_64")]
            Expander::Pdep(e) => e.compact_slice(codes, out),
        }
    }
}

/// `out[i] = f(src[i])` for each pair of elements (up to the shorter slice): the per-element
/// loop of the slice methods of the portable backends.
#[inline]
fn each<A: Copy, B>(src: &[A], out: &mut [B], f: impl Fn(A) -> B) {
    for (o, &a) in out.iter_mut().zip(src) {
        *o = f(a);
    }
}
