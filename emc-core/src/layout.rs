//! Code layouts: which channel (x, y, z or size) owns each bit of a code, MSB first.
//! A [`LayoutSpec`] is a name (`morton63`, `emc64-var`, `custom:xxyszz…`); resolving it against a
//! scene [`Frame`](crate::Frame) gives a concrete [`Layout`], the data every backend is built from.
//!
//! Decisions on the open questions of the EMC definition (all documented once, here):
//!
//! | question | decision |
//! |---|---|
//! | size measure | Euclidean length of the primitive box diagonal `d` |
//! | size normalisation | `d / D`, `D` = diagonal of the union of primitive boxes |
//! | size transform | `sqrt` for the `-var` layouts and custom patterns (default), linear for `emc64-sort` and `custom:…:linear` |
//! | size placement (`-var`) | fixed period 7: 0-based positions 6, 13, 20, … ; 6 size bits in 64, 4 in 32 |
//! | do size bits consume halving steps | no: the spatial schedule runs over the spatial positions only |
//! | axis tie-break in the halving | x > y > z (strictly longer extent wins) |
//! | box for positions | the centroid box, per axis ([`Normalization::CentroidBox`]); primitive box and cube are options |
//! | quantiser | `floor(offset · 2^n / E)` clamped to `[0, 2^n − 1]` (never `2^n − 1` scaling, never wraps) |
//! | code width | `morton30`, `morton63`: 30/63 bits; `-var` and `-sort`: full 32/64 bits |
//! | baseline Morton normalisation | per axis by default; the cube is [`Normalization::Cube`] |
//! | separable features | size, variable bits and adaptive order are separable through `custom:` patterns |
//! | duplicate codes in LBVH | equal codes are extended by their sorted position (emc-cpu) |
//! | zero-extent axis | gets no bits in the adaptive layouts; its value is 0 when a fixed layout gives it bits |
//! | all extents zero | the halving rule falls back to round-robin x, y, z |
#![forbid(unsafe_code)]

use core::fmt;
use core::str::FromStr;

use crate::error::Error;

/// One channel of a code: a spatial axis or the size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u8)]
pub enum Channel {
    /// The x axis.
    X = 0,
    /// The y axis.
    Y = 1,
    /// The z axis.
    Z = 2,
    /// The primitive size.
    S = 3,
}

impl Channel {
    /// All four channels in index order.
    pub const ALL: [Channel; 4] = [Channel::X, Channel::Y, Channel::Z, Channel::S];

    /// The channel's index (x 0, y 1, z 2, s 3).
    #[inline]
    pub const fn index(self) -> usize {
        self as usize
    }

    /// The channel with this index (0..=3).
    #[inline]
    pub const fn from_index(i: usize) -> Channel {
        match i & 3 {
            0 => Channel::X,
            1 => Channel::Y,
            2 => Channel::Z,
            _ => Channel::S,
        }
    }

    /// The pattern letter (`x`, `y`, `z`, `s`).
    #[inline]
    pub const fn letter(self) -> char {
        match self {
            Channel::X => 'x',
            Channel::Y => 'y',
            Channel::Z => 'z',
            Channel::S => 's',
        }
    }

    /// The channel for a pattern letter (either case).
    pub const fn from_letter(c: char) -> Option<Channel> {
        match c {
            'x' | 'X' => Some(Channel::X),
            'y' | 'Y' => Some(Channel::Y),
            'z' | 'Z' => Some(Channel::Z),
            's' | 'S' => Some(Channel::S),
            _ => None,
        }
    }
}

impl fmt::Display for Channel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.letter())
    }
}

/// How the size value `σ = d / D` becomes the number that the size bits quantise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum SizeTransform {
    /// `sqrt(σ)`: size bit `k` flips at `D / 4^k`, the cell diagonal when a size bit sits every
    /// two octree levels (period 7).
    #[default]
    Sqrt,
    /// `σ` itself: size bit `k` flips at `D / 2^k` (the seed's listing, uniform `xyzs`).
    Linear,
}

impl fmt::Display for SizeTransform {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            SizeTransform::Sqrt => "sqrt",
            SizeTransform::Linear => "linear",
        })
    }
}

/// Which box the positions are normalised to (per axis unless `Cube`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum Normalization {
    /// The box of the primitive centres, each axis stretched to `[0, 1]` (the default).
    #[default]
    CentroidBox,
    /// The union of the primitive boxes, each axis stretched to `[0, 1]`.
    PrimitiveBox,
    /// A cube anchored at the centroid box minimum with the edge of its longest axis (PLOC-style
    /// baseline: short axes waste their top bits). Adaptive layouts then see a cube.
    Cube,
}

impl fmt::Display for Normalization {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Normalization::CentroidBox => "centroid-box",
            Normalization::PrimitiveBox => "primitive-box",
            Normalization::Cube => "cube",
        })
    }
}

impl FromStr for Normalization {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        match s {
            "centroid-box" | "centroid" => Ok(Normalization::CentroidBox),
            "primitive-box" | "primitive" => Ok(Normalization::PrimitiveBox),
            "cube" => Ok(Normalization::Cube),
            _ => Err(Error::BadLayoutOption),
        }
    }
}

/// A fixed pattern of up to 64 channels, MSB first, with its size transform.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Pattern {
    chans: [Channel; 64],
    len: u8,
    transform: SizeTransform,
}

impl fmt::Debug for Pattern {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Pattern(")?;
        for c in self.channels() {
            write!(f, "{c}")?;
        }
        write!(f, ", {})", self.transform)
    }
}

impl Pattern {
    /// Parse `xxyszz…` (1..=64 letters, each channel at most 32 bits).
    pub fn parse(s: &str, transform: SizeTransform) -> Result<Pattern, Error> {
        let n = s.chars().count();
        if n == 0 {
            return Err(Error::EmptyPattern);
        }
        if n > 64 {
            return Err(Error::PatternTooLong(n));
        }
        let mut chans = [Channel::X; 64];
        let mut counts = [0u32; 4];
        for (i, c) in s.chars().enumerate() {
            let ch = Channel::from_letter(c).ok_or(Error::BadPatternChar(c, i))?;
            chans[i] = ch;
            counts[ch.index()] += 1;
        }
        for ch in Channel::ALL {
            if counts[ch.index()] > 32 {
                return Err(Error::ChannelTooWide(ch, counts[ch.index()]));
            }
        }
        Ok(Pattern {
            chans,
            len: n as u8,
            transform,
        })
    }

    /// The channels, MSB first.
    #[inline]
    pub fn channels(&self) -> &[Channel] {
        &self.chans[..self.len as usize]
    }

    /// The size transform.
    #[inline]
    pub fn transform(&self) -> SizeTransform {
        self.transform
    }
}

/// A layout by name: what the CLI, CSV files and docs call it. Adaptive layouts become a
/// concrete [`Layout`] only against a scene frame ([`LayoutSpec::resolve`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LayoutSpec {
    /// 30-bit Morton code, 10/10/10, `(xyz)^10`, x most significant.
    Morton30,
    /// 63-bit Morton code, 21/21/21, `(xyz)^21` (the seed's "MC-64").
    Morton63,
    /// The seed's listing: axes by descending extent, 16 bits each plus 16 linear size bits,
    /// `(a0 a1 a2 s)^16`.
    Emc64Sort,
    /// 64 bits: 6 sqrt-size bits at positions 6, 13, …, 41; 58 spatial bits by longest-extent
    /// halving.
    Emc64Var,
    /// 32 bits: 4 sqrt-size bits at positions 6, 13, 20, 27; 28 spatial bits by halving.
    Emc32Var,
    /// 64 spatial bits by longest-extent halving, no size bits.
    Emc64VarNoSize,
    /// Any fixed pattern (`custom:PATTERN`, optionally `:linear` or `:sqrt`).
    Custom(Pattern),
}

impl LayoutSpec {
    /// The six standard layouts, in the order tables list them.
    pub const STANDARD: [LayoutSpec; 6] = [
        LayoutSpec::Morton30,
        LayoutSpec::Morton63,
        LayoutSpec::Emc32Var,
        LayoutSpec::Emc64Sort,
        LayoutSpec::Emc64Var,
        LayoutSpec::Emc64VarNoSize,
    ];

    /// Number of code bits this layout produces.
    pub fn width(&self) -> u32 {
        match self {
            LayoutSpec::Morton30 => 30,
            LayoutSpec::Morton63 => 63,
            LayoutSpec::Emc32Var => 32,
            LayoutSpec::Emc64Sort | LayoutSpec::Emc64Var | LayoutSpec::Emc64VarNoSize => 64,
            LayoutSpec::Custom(p) => p.len as u32,
        }
    }

    /// Whether the layout depends on the scene's extents (the adaptive ones).
    pub fn is_adaptive(&self) -> bool {
        matches!(
            self,
            LayoutSpec::Emc64Sort
                | LayoutSpec::Emc64Var
                | LayoutSpec::Emc32Var
                | LayoutSpec::Emc64VarNoSize
        )
    }

    /// The concrete layout for a scene whose position box has extents `extent` (x, y, z).
    pub fn resolve(&self, extent: [f64; 3]) -> Layout {
        let mut l = Layout {
            spec: *self,
            chans: [Channel::X; 64],
            len: 0,
            bits: [0; 4],
            transform: SizeTransform::Sqrt,
        };
        match self {
            LayoutSpec::Morton30 => l.fill_regular(&[Channel::X, Channel::Y, Channel::Z], 10),
            LayoutSpec::Morton63 => l.fill_regular(&[Channel::X, Channel::Y, Channel::Z], 21),
            LayoutSpec::Emc64Sort => {
                let order = axes_by_descending_extent(extent);
                l.fill_regular(&[order[0], order[1], order[2], Channel::S], 16);
                l.transform = SizeTransform::Linear;
            }
            LayoutSpec::Emc64Var => l.fill_halving(extent, 64, 7, 6),
            LayoutSpec::Emc32Var => l.fill_halving(extent, 32, 7, 4),
            LayoutSpec::Emc64VarNoSize => l.fill_halving(extent, 64, 7, 0),
            LayoutSpec::Custom(p) => {
                for &c in p.channels() {
                    l.push(c);
                }
                l.transform = p.transform;
            }
        }
        l
    }
}

impl fmt::Display for LayoutSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LayoutSpec::Morton30 => f.write_str("morton30"),
            LayoutSpec::Morton63 => f.write_str("morton63"),
            LayoutSpec::Emc64Sort => f.write_str("emc64-sort"),
            LayoutSpec::Emc64Var => f.write_str("emc64-var"),
            LayoutSpec::Emc32Var => f.write_str("emc32-var"),
            LayoutSpec::Emc64VarNoSize => f.write_str("emc64-var-nosize"),
            LayoutSpec::Custom(p) => {
                f.write_str("custom:")?;
                for c in p.channels() {
                    write!(f, "{c}")?;
                }
                if p.transform == SizeTransform::Linear {
                    f.write_str(":linear")?;
                }
                Ok(())
            }
        }
    }
}

impl FromStr for LayoutSpec {
    type Err = Error;
    /// Parse a layout name. `custom:PATTERN[:sqrt|:linear]`; names are case-sensitive.
    fn from_str(s: &str) -> Result<Self, Error> {
        Ok(match s {
            "morton30" => LayoutSpec::Morton30,
            "morton63" => LayoutSpec::Morton63,
            "emc64-sort" => LayoutSpec::Emc64Sort,
            "emc64-var" => LayoutSpec::Emc64Var,
            "emc32-var" => LayoutSpec::Emc32Var,
            "emc64-var-nosize" => LayoutSpec::Emc64VarNoSize,
            _ => {
                let rest = s.strip_prefix("custom:").ok_or(Error::UnknownLayout)?;
                let (pat, transform) = match rest.split_once(':') {
                    None => (rest, SizeTransform::Sqrt),
                    Some((p, "sqrt")) => (p, SizeTransform::Sqrt),
                    Some((p, "linear")) => (p, SizeTransform::Linear),
                    Some(_) => return Err(Error::BadLayoutOption),
                };
                LayoutSpec::Custom(Pattern::parse(pat, transform)?)
            }
        })
    }
}

/// Axes sorted by descending extent; stable, so equal extents keep the order x, y, z.
pub fn axes_by_descending_extent(e: [f64; 3]) -> [Channel; 3] {
    let mut order = [Channel::X, Channel::Y, Channel::Z];
    // Insertion sort of three: stable by construction (moves only on strictly greater).
    for i in 1..3 {
        let mut j = i;
        while j > 0 && e[order[j].index()] > e[order[j - 1].index()] {
            order.swap(j, j - 1);
            j -= 1;
        }
    }
    order
}

/// The spatial schedule of the halving rule: `n` axes, MSB first. Each step picks the axis with
/// the currently longest extent (ties x > y > z) and halves it; halving is exact in `f64`, so the
/// rule is exact at powers of two. A scene with every extent zero falls back to round robin.
pub fn halving_schedule(extent: [f64; 3], n: usize, out: &mut [Channel]) {
    let mut e = extent;
    for (i, slot) in out.iter_mut().enumerate().take(n) {
        let mut a = 0;
        if e[1] > e[a] {
            a = 1;
        }
        if e[2] > e[a] {
            a = 2;
        }
        if e[a] <= 0.0 {
            a = i % 3;
        }
        *slot = Channel::from_index(a);
        e[a] *= 0.5;
    }
}

/// A concrete layout: `len` positions (≤ 64), MSB first, each owned by one channel, plus the
/// size transform. Codes are right-aligned: position 0 is bit `len − 1` of the word.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Layout {
    spec: LayoutSpec,
    chans: [Channel; 64],
    len: u8,
    bits: [u8; 4],
    transform: SizeTransform,
}

impl fmt::Debug for Layout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Layout({} {self})", self.spec)
    }
}

impl Layout {
    fn push(&mut self, c: Channel) {
        self.chans[self.len as usize] = c;
        self.len += 1;
        self.bits[c.index()] += 1;
    }

    fn fill_regular(&mut self, order: &[Channel], per: usize) {
        for _ in 0..per {
            for &c in order {
                self.push(c);
            }
        }
    }

    fn fill_halving(&mut self, extent: [f64; 3], n: usize, period: usize, size_bits: usize) {
        let spatial_n = n - size_bits;
        let mut spatial = [Channel::X; 64];
        halving_schedule(extent, spatial_n, &mut spatial);
        let mut next = 0;
        let mut placed = 0;
        for k in 0..n {
            if placed < size_bits && (k + 1) % period == 0 {
                self.push(Channel::S);
                placed += 1;
            } else {
                self.push(spatial[next]);
                next += 1;
            }
        }
        self.transform = SizeTransform::Sqrt;
    }

    /// A layout from an explicit pattern without the 32-bit-per-channel cap of custom names
    /// (adaptive layouts of extreme scenes give one axis more than 32 bits).
    pub fn from_channels(chans: &[Channel], transform: SizeTransform) -> Result<Layout, Error> {
        if chans.is_empty() {
            return Err(Error::EmptyPattern);
        }
        if chans.len() > 64 {
            return Err(Error::PatternTooLong(chans.len()));
        }
        let mut p = Pattern {
            chans: [Channel::X; 64],
            len: chans.len() as u8,
            transform,
        };
        p.chans[..chans.len()].copy_from_slice(chans);
        let mut l = Layout {
            spec: LayoutSpec::Custom(p),
            chans: p.chans,
            len: 0,
            bits: [0; 4],
            transform,
        };
        for &c in chans {
            l.push(c);
        }
        Ok(l)
    }

    /// The name this layout was resolved from.
    #[inline]
    pub fn spec(&self) -> LayoutSpec {
        self.spec
    }

    /// Number of code bits (positions).
    #[inline]
    pub fn len(&self) -> u32 {
        self.len as u32
    }

    /// Never true: a layout has at least one position. Present for API symmetry.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// True when codes fit a `u32`.
    #[inline]
    pub fn fits_u32(&self) -> bool {
        self.len <= 32
    }

    /// The channel of every position, MSB first.
    #[inline]
    pub fn channels(&self) -> &[Channel] {
        &self.chans[..self.len as usize]
    }

    /// Bits owned by a channel.
    #[inline]
    pub fn bits(&self, c: Channel) -> u32 {
        self.bits[c.index()] as u32
    }

    /// Bits of the four channels (x, y, z, s).
    #[inline]
    pub fn bit_counts(&self) -> [u32; 4] {
        [
            self.bits[0] as u32,
            self.bits[1] as u32,
            self.bits[2] as u32,
            self.bits[3] as u32,
        ]
    }

    /// The size transform.
    #[inline]
    pub fn transform(&self) -> SizeTransform {
        self.transform
    }

    /// For each channel, the mask of code-word bits it owns (the `pdep`/`pext` masks).
    pub fn masks(&self) -> [u64; 4] {
        let mut m = [0u64; 4];
        let n = self.len as u32;
        for (k, c) in self.channels().iter().enumerate() {
            m[c.index()] |= 1u64 << (n - 1 - k as u32);
        }
        m
    }

    /// The largest value a channel may hold (`2^bits − 1`, 0 for an unused channel).
    #[inline]
    pub fn channel_max(&self, c: Channel) -> u64 {
        let b = self.bits(c);
        if b == 0 {
            0
        } else {
            u64::MAX >> (64 - b)
        }
    }

    /// The seed-style bit-count line, e.g. `20/19/19/6`.
    pub fn counts_line(&self) -> impl fmt::Display + '_ {
        struct Counts<'a>(&'a Layout);
        impl fmt::Display for Counts<'_> {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                let b = self.0.bit_counts();
                write!(f, "{}/{}/{}/{}", b[0], b[1], b[2], b[3])
            }
        }
        Counts(self)
    }

    /// The pattern as letters, MSB first.
    pub fn pattern_str(&self) -> impl fmt::Display + '_ {
        struct P<'a>(&'a Layout);
        impl fmt::Display for P<'_> {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                for c in self.0.channels() {
                    write!(f, "{c}")?;
                }
                Ok(())
            }
        }
        P(self)
    }
}

impl fmt::Display for Layout {
    /// The seed-style line: bit counts x/y/z/s, then the pattern MSB first.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}", self.counts_line(), self.pattern_str())
    }
}
