//! Errors of emc-core: small `Copy` values, one documented variant per way user data can be wrong.
//! Nothing in emc-core panics on user data; every fallible constructor returns [`Error`].
#![forbid(unsafe_code)]

use core::fmt;

use crate::layout::Channel;

/// Everything that can go wrong when building layouts, frames and encoders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Error {
    /// A layout name that is not one of the standard names nor `custom:PATTERN`.
    UnknownLayout,
    /// A custom pattern with no positions.
    EmptyPattern,
    /// A custom pattern longer than 64 positions; carries the length found.
    PatternTooLong(usize),
    /// A character in a custom pattern that is not `x`, `y`, `z` or `s`; carries the character
    /// and its 0-based position.
    BadPatternChar(char, usize),
    /// A channel that owns more than 32 bits in a custom pattern; carries the channel and count.
    ChannelTooWide(Channel, u32),
    /// An unknown option after the pattern (`:sqrt` and `:linear` are the known ones).
    BadLayoutOption,
    /// The frame was asked for with no primitives.
    EmptyScene,
    /// A primitive box has a NaN or infinite coordinate; carries the primitive index.
    NonFinite(usize),
    /// A primitive box whose minimum exceeds its maximum on some axis; carries the index.
    InvertedBox(usize),
    /// An output buffer of the wrong length: (expected, found).
    LengthMismatch(usize, usize),
    /// A code wider than 32 bits was asked for in a `u32` buffer; carries the layout width.
    CodeTooWide(u32),
    /// A backend that was forced but cannot serve this layout on this CPU.
    BackendUnavailable(crate::Backend),
    /// A backend name that is not one of `reference`, `magic`, `table`, `pdep`.
    UnknownBackend,
    /// A quantise path that was forced but cannot serve this layout on this CPU (AVX2 needs
    /// x86_64 with AVX2 and channels of at most 31 bits).
    QuantizeUnavailable(crate::simd::QuantizePath),
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Error::UnknownLayout => write!(
                f,
                "unknown layout (expected morton30, morton63, emc64-sort, emc64-var, emc32-var, \
                 emc64-var-nosize or custom:PATTERN)"
            ),
            Error::EmptyPattern => write!(f, "custom layout pattern is empty"),
            Error::PatternTooLong(n) => {
                write!(
                    f,
                    "custom layout pattern has {n} positions, at most 64 are allowed"
                )
            }
            Error::BadPatternChar(c, i) => write!(
                f,
                "custom layout pattern has {c:?} at position {i}; only x, y, z and s are allowed"
            ),
            Error::ChannelTooWide(ch, n) => {
                write!(
                    f,
                    "custom layout gives channel {ch} {n} bits, at most 32 are allowed"
                )
            }
            Error::BadLayoutOption => {
                write!(
                    f,
                    "unknown layout option (expected `:sqrt` or `:linear` after the pattern)"
                )
            }
            Error::EmptyScene => write!(f, "the scene has no primitives"),
            Error::NonFinite(i) => {
                write!(f, "primitive {i} has a NaN or infinite coordinate")
            }
            Error::InvertedBox(i) => write!(f, "primitive {i} has a box whose min exceeds its max"),
            Error::LengthMismatch(e, g) => {
                write!(
                    f,
                    "output buffer holds {g} codes but {e} primitives were given"
                )
            }
            Error::CodeTooWide(n) => {
                write!(f, "the layout has {n} bits, which does not fit a u32 code")
            }
            Error::BackendUnavailable(b) => {
                write!(f, "backend {b} cannot serve this layout on this CPU")
            }
            Error::UnknownBackend => write!(
                f,
                "unknown backend (expected reference, magic, table or pdep)"
            ),
            Error::QuantizeUnavailable(q) => write!(
                f,
                "quantize path {q} cannot serve this layout on this CPU (avx2 needs x86_64 \
                 with AVX2 and channels of at most 31 bits)"
            ),
        }
    }
}

impl core::error::Error for Error {}
