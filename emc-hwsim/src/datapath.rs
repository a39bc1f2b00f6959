//! The unit's datapath: configuration registers loaded per layout and frame, the named pipeline
//! stages they instantiate (only those the configuration needs), and the stage operations that
//! compute every code — fp64 adders and multipliers, float→fixed, size comparators or the
//! sqrt/divide path, and the routing network — without calling emc-core's encoder.
#![forbid(unsafe_code)]

use core::fmt;

use emc_core::{Aabb, Channel, Frame, Layout, LayoutSpec, SizeTransform};

use crate::error::HwError;
use crate::firmware::{is_regular, position_scale, size_thresholds};
use crate::fixed::{compare_key, exp_add, float_to_fixed};
use crate::routing::{
    field_offsets, layout_permutation, morton_wires, permute, Benes, Crossbar, Permutation,
};

/// Which interleave hardware to build.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum RoutingChoice {
    /// Fixed wiring for regular fixed patterns (`morton30`, `morton63`, and `custom:` patterns
    /// that repeat one group of distinct channels), a Beneš network for everything else.
    #[default]
    Auto,
    /// Fixed wiring (only for regular fixed patterns).
    Fixed,
    /// A Beneš network (2 pipeline cycles).
    Benes,
    /// A full crossbar (1 pipeline cycle).
    Crossbar,
}

impl core::str::FromStr for RoutingChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(RoutingChoice::Auto),
            "fixed" => Ok(RoutingChoice::Fixed),
            "benes" => Ok(RoutingChoice::Benes),
            "crossbar" => Ok(RoutingChoice::Crossbar),
            _ => Err(format!(
                "unknown routing {s:?} (expected auto, fixed, benes or crossbar)"
            )),
        }
    }
}

/// How the threshold size unit finds the count of thresholds below `d2`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum SizeSearch {
    /// `S` pipelined binary-search steps, one comparator each.
    #[default]
    Binary,
    /// `2^S − 1` comparators in parallel plus a population count (2 cycles).
    Bank,
}

/// Knobs of the unit that do not come from the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UnitOptions {
    /// Parallel datapath lanes (codes accepted per cycle at most).
    pub lanes: u32,
    /// Interleave hardware.
    pub routing: RoutingChoice,
    /// Threshold search structure (layouts with `1 <= S <= 8`).
    pub size_search: SizeSearch,
    /// Use an iterative (non-pipelined, II = latency) sqrt/divide unit instead of a pipelined
    /// one on the formula size path (`S > 8`, e.g. `emc64-sort`).
    pub iterative_formula: bool,
    /// Input buffer capacity in AABBs.
    pub input_capacity: u32,
    /// Output FIFO capacity in codes; 0 sizes it to the codes in flight (Little's law:
    /// `lanes × depth` plus two write bursts, rounded up to a whole burst), see
    /// [`Unit::output_capacity`]. A smaller FIFO throttles entry through its credits.
    pub output_capacity: u32,
    /// AABBs per read burst (24 bytes each).
    pub read_burst: u32,
    /// Bytes per write burst (a multiple of the code size is used).
    pub write_burst_bytes: u32,
}

impl Default for UnitOptions {
    fn default() -> Self {
        UnitOptions {
            lanes: 1,
            routing: RoutingChoice::Auto,
            size_search: SizeSearch::Binary,
            iterative_formula: false,
            input_capacity: 256,
            output_capacity: 0,
            read_burst: 8,
            write_burst_bytes: 64,
        }
    }
}

/// The size channel as instantiated.
#[derive(Clone, Debug, PartialEq)]
pub enum SizeUnit {
    /// No size bits: the whole size path is absent.
    None,
    /// `1 <= S <= 8`: `2^S − 1` threshold registers on `d2` (comparator keys; index 0 unused).
    Thresholds {
        /// Size bits `S`.
        bits: u32,
        /// `keys[k]` = bit pattern of the smallest `d2` whose size value is `>= k`.
        keys: Vec<u64>,
    },
    /// `S > 8`: fp64 sqrt and divide in the normative order.
    Formula {
        /// Size bits `S`.
        bits: u32,
        /// Linear (`sqrt(d2)·2^S / D`) or sqrt (`sqrt(sqrt(d2) / D)·2^S`).
        transform: SizeTransform,
        /// Frame diagonal `D`.
        diag: f64,
    },
}

/// The interleave as instantiated.
#[derive(Clone, Debug, PartialEq)]
pub enum Network {
    /// Wires of a regular fixed pattern: no logic, no configuration.
    Fixed {
        /// Code bit `j` is packed bit `src[j]`.
        src: Box<Permutation>,
        /// `Some(n)` for Morton wires `(xyz)^n` (the model's shift-and-mask path).
        morton: Option<u32>,
    },
    /// A Beneš network with per-frame control bits.
    Benes(Benes),
    /// A crossbar with per-frame selects.
    Crossbar(Crossbar),
}

impl Network {
    /// Short name.
    pub fn name(&self) -> &'static str {
        match self {
            Network::Fixed { .. } => "fixed wiring",
            Network::Benes(_) => "Beneš network",
            Network::Crossbar(_) => "crossbar",
        }
    }
}

/// Configuration registers of one unit for one layout and frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Registers {
    /// Axes with at least one bit (their position lane is instantiated).
    pub axis_on: [bool; 3],
    /// `2·origin` per axis (subtracted from `lo + hi`).
    pub origin2: [f64; 3],
    /// `2^n / E / 2` per axis (0 on a flat axis).
    pub half_scale: [f64; 3],
    /// Bits per channel (x, y, z, s).
    pub bits: [u32; 4],
    /// Field offsets of the packed routing word.
    pub offset: [u32; 4],
    /// Code length in bits.
    pub len: u32,
    /// Size channel.
    pub size: SizeUnit,
    /// Interleave.
    pub net: Network,
}

impl Registers {
    /// Load the registers from a resolved layout and its frame, as the firmware would: the
    /// position scales, size thresholds and routing controls come from [`crate::firmware`]
    /// and the routing algorithms, not from emc-core's quantiser.
    pub fn load(layout: &Layout, frame: &Frame, opts: &UnitOptions) -> Result<Registers, HwError> {
        Registers::program(layout, layout.spec().is_adaptive(), frame, opts)
    }

    /// [`Registers::load`] for a layout whose name may be adaptive (its pattern then depends on
    /// the frame, so the interleave must be programmable).
    pub fn program(
        layout: &Layout,
        adaptive: bool,
        frame: &Frame,
        opts: &UnitOptions,
    ) -> Result<Registers, HwError> {
        let bits = layout.bit_counts();
        let o = frame.origin();
        let e = frame.extent();
        let mut origin2 = [0.0; 3];
        let mut half_scale = [0.0; 3];
        let mut axis_on = [false; 3];
        for a in 0..3 {
            axis_on[a] = bits[a] > 0;
            origin2[a] = 2.0 * o[a];
            half_scale[a] = if e[a] > 0.0 && bits[a] > 0 {
                position_scale(bits[a], e[a]) * 0.5
            } else {
                0.0
            };
        }
        let s = bits[3];
        let size = if s == 0 {
            SizeUnit::None
        } else if s <= MAX_THRESHOLD_BITS {
            SizeUnit::Thresholds {
                bits: s,
                keys: size_thresholds(s, layout.transform(), frame.diagonal()),
            }
        } else {
            SizeUnit::Formula {
                bits: s,
                transform: layout.transform(),
                diag: frame.diagonal(),
            }
        };
        let len = layout.len();
        let chans = layout.channels();
        let regular = !adaptive && is_regular(chans);
        let morton = (bits[3] == 0
            && bits[0] <= 21
            && chans
                .chunks(3)
                .all(|g| g == [Channel::X, Channel::Y, Channel::Z]))
        .then_some(bits[0]);
        let lanes_k = if len <= 32 { 5 } else { 6 };
        let perm = layout_permutation(layout);
        let net = match (opts.routing, regular) {
            (RoutingChoice::Auto | RoutingChoice::Fixed, true) => Network::Fixed {
                src: Box::new(perm),
                morton,
            },
            (RoutingChoice::Fixed, false) => {
                return Err(HwError::NotFixedLayout(layout.pattern_str().to_string()))
            }
            (RoutingChoice::Auto | RoutingChoice::Benes, _) => {
                Network::Benes(Benes::route(&perm, lanes_k))
            }
            (RoutingChoice::Crossbar, _) => Network::Crossbar(Crossbar::new(&perm, 1 << lanes_k)),
        };
        Ok(Registers {
            axis_on,
            origin2,
            half_scale,
            bits,
            offset: field_offsets(bits),
            len,
            size,
            net,
        })
    }

    /// Size bits (0 when the size path is absent).
    pub fn size_bits(&self) -> u32 {
        self.bits[3]
    }
}

/// What a stage does (its operation on the token, applied when the stage completes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Op {
    /// Split the 24-byte record into `lo` and `hi` (a register stage).
    Unpack,
    /// `c2 = lo + hi` per active axis ∥ size: `Δ = hi − lo`.
    Centre,
    /// `c2 − 2·origin` ∥ size: `Δ²`.
    Offset,
    /// `× half_scale` ∥ size: `Δx² + Δy²`.
    Scale,
    /// float→fixed with clamp per active axis ∥ size: `+ Δz²`.
    Fix,
    /// Binary threshold search, step `k` (stride `2^(S−1−k)`).
    SearchStep(u32),
    /// Comparator bank and population count.
    Bank,
    /// fp64 square root of `d2`.
    Sqrt,
    /// `× 2^S` by exponent add.
    SizeScale,
    /// fp64 divide by `D`.
    Div,
    /// fp64 square root of `d / D` (sqrt transform).
    Sqrt2,
    /// float→fixed with clamp of the size value.
    SizeFix,
    /// Pack fields and pass network columns `from..to` (Beneš) or the whole crossbar.
    Route(u8, u8),
    /// Write the code word (fixed wiring happens here: it is only wires).
    Pack,
}

/// One named pipeline stage.
#[derive(Clone, Debug, PartialEq)]
pub struct Stage {
    /// Name in the structure printout.
    pub name: &'static str,
    /// Cycles from entry to result.
    pub latency: u32,
    /// Initiation interval (cycles between accepted tokens).
    pub ii: u32,
    /// Operation applied on completion.
    pub op: Op,
    /// What hardware the stage instantiates (for the printout).
    pub hw: String,
}

/// Largest size-bit count served by threshold registers (the formula path above).
pub const MAX_THRESHOLD_BITS: u32 = 8;

/// Latency of the 3-stage fp64 adder and multiplier (DesignWare-class, 1 GHz at 40 nm).
pub const FP_LATENCY: u32 = 3;
/// Latency of a pipelined fp64 square root or divider (multiplicative, assumed).
pub const SQRT_DIV_PIPELINED_LATENCY: u32 = 12;
/// Latency (= initiation interval) of an iterative radix-4 fp64 square root or divider.
pub const SQRT_DIV_ITERATIVE_LATENCY: u32 = 28;

/// The intermediate values a token carries down the pipeline.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Token {
    /// Primitive index (for ordering checks).
    pub index: u64,
    lo: [f32; 3],
    hi: [f32; 3],
    c2: [f64; 3],
    dl: [f64; 3],
    acc: f64,
    d2: f64,
    q: [u64; 4],
    pos: u64,
    sd: f64,
    word: u64,
}

impl Token {
    /// A token for a box entering the unit.
    pub fn new(index: u64, b: &Aabb) -> Token {
        Token {
            index,
            lo: b.min.to_array(),
            hi: b.max.to_array(),
            ..Token::default()
        }
    }

    /// The finished code (valid after the pack stage).
    pub fn code(&self) -> u64 {
        self.word
    }
}

/// A configured unit: registers plus the stage list they instantiate.
#[derive(Clone, Debug)]
pub struct Unit {
    regs: Registers,
    stages: Vec<Stage>,
    opts: UnitOptions,
    layout: Layout,
    spec: LayoutSpec,
}

impl Unit {
    /// Configure a unit for a layout in a frame.
    pub fn new(layout: &Layout, frame: &Frame, opts: &UnitOptions) -> Result<Unit, HwError> {
        Unit::build(layout.spec(), *layout, frame, opts)
    }

    /// Configure a unit for a layout name: the firmware derives the bit schedule from the
    /// frame ([`crate::firmware::schedule`]), then the registers are loaded.
    pub fn for_spec(spec: &LayoutSpec, frame: &Frame, opts: &UnitOptions) -> Result<Unit, HwError> {
        let (chans, transform) = crate::firmware::schedule(spec, frame.extent());
        let layout = Layout::from_channels(&chans, transform).map_err(HwError::Layout)?;
        Unit::build(*spec, layout, frame, opts)
    }

    fn build(
        spec: LayoutSpec,
        layout: Layout,
        frame: &Frame,
        opts: &UnitOptions,
    ) -> Result<Unit, HwError> {
        if opts.lanes == 0 {
            return Err(HwError::NoLanes(0));
        }
        let regs = Registers::program(&layout, spec.is_adaptive(), frame, opts)?;
        let stages = build_stages(&regs, opts);
        Ok(Unit {
            regs,
            stages,
            opts: *opts,
            layout,
            spec,
        })
    }

    /// The layout name the unit was configured for.
    pub fn spec(&self) -> LayoutSpec {
        self.spec
    }

    /// The registers.
    pub fn registers(&self) -> &Registers {
        &self.regs
    }

    /// The instantiated stages, in pipeline order.
    pub fn stages(&self) -> &[Stage] {
        &self.stages
    }

    /// The options the unit was built with.
    pub fn options(&self) -> &UnitOptions {
        &self.opts
    }

    /// The layout.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// Pipeline depth in cycles (sum of stage latencies).
    pub fn depth(&self) -> u32 {
        self.stages.iter().map(|s| s.latency).sum()
    }

    /// Initiation interval of one lane (the largest stage II).
    pub fn lane_ii(&self) -> u32 {
        self.stages.iter().map(|s| s.ii).max().unwrap_or(1)
    }

    /// Codes per write burst.
    pub fn write_burst(&self) -> u32 {
        if self.opts.write_burst_bytes == 0 {
            0
        } else {
            (self.opts.write_burst_bytes / self.code_bytes()).max(1)
        }
    }

    /// The output FIFO capacity in codes (the option, or the automatic size when it is 0).
    pub fn output_capacity(&self) -> u32 {
        if self.opts.output_capacity > 0 {
            return self.opts.output_capacity;
        }
        let wb = self.write_burst().max(1);
        (self.opts.lanes * self.depth() + 2 * wb).div_ceil(wb) * wb
    }

    /// Bytes per code word written (4 for codes of at most 32 bits, else 8).
    pub fn code_bytes(&self) -> u32 {
        if self.regs.len <= 32 {
            4
        } else {
            8
        }
    }

    /// Apply one stage's operation to a token.
    #[inline]
    pub fn apply(&self, op: Op, t: &mut Token) {
        let r = &self.regs;
        let size = !matches!(r.size, SizeUnit::None);
        match op {
            Op::Unpack => {}
            Op::Centre => {
                for a in 0..3 {
                    if r.axis_on[a] {
                        t.c2[a] = t.lo[a] as f64 + t.hi[a] as f64;
                    }
                    if size {
                        t.dl[a] = t.hi[a] as f64 - t.lo[a] as f64;
                    }
                }
            }
            Op::Offset => {
                for a in 0..3 {
                    if r.axis_on[a] {
                        t.c2[a] -= r.origin2[a];
                    }
                    if size {
                        t.dl[a] *= t.dl[a];
                    }
                }
            }
            Op::Scale => {
                for a in 0..3 {
                    if r.axis_on[a] {
                        t.c2[a] *= r.half_scale[a];
                    }
                }
                if size {
                    t.acc = t.dl[0] + t.dl[1];
                }
            }
            Op::Fix => {
                for a in 0..3 {
                    if r.axis_on[a] {
                        t.q[a] = float_to_fixed(t.c2[a], r.bits[a]);
                    }
                }
                if size {
                    t.d2 = t.acc + t.dl[2];
                }
            }
            Op::SearchStep(k) => {
                if let SizeUnit::Thresholds { bits, keys } = &r.size {
                    let stride = 1u64 << (bits - 1 - k);
                    let key = compare_key(t.d2);
                    t.pos += stride * (keys[(t.pos + stride) as usize] <= key) as u64;
                    t.q[3] = t.pos;
                }
            }
            Op::Bank => {
                if let SizeUnit::Thresholds { keys, .. } = &r.size {
                    let key = compare_key(t.d2);
                    t.q[3] = keys[1..].iter().filter(|&&k| k <= key).count() as u64;
                }
            }
            Op::Sqrt => t.sd = t.d2.sqrt(),
            Op::SizeScale => t.sd = exp_add(t.sd, r.bits[3]),
            Op::Div => {
                if let SizeUnit::Formula { diag, .. } = r.size {
                    t.sd /= diag;
                }
            }
            Op::Sqrt2 => t.sd = t.sd.sqrt(),
            Op::SizeFix => t.q[3] = float_to_fixed(t.sd, r.bits[3]),
            Op::Route(from, to) => {
                if from == 0 {
                    t.word = self.packed(&t.q);
                }
                match &r.net {
                    Network::Benes(b) => {
                        t.word = b.apply_columns(t.word, from as usize..to as usize)
                    }
                    Network::Crossbar(x) => t.word = x.apply(t.word),
                    Network::Fixed { .. } => {}
                }
            }
            Op::Pack => {
                if let Network::Fixed { src, morton } = &r.net {
                    t.word = match morton {
                        Some(_) => morton_wires(t.q[0], t.q[1], t.q[2]),
                        None => permute(src, self.packed(&t.q), r.len),
                    };
                }
            }
        }
    }

    /// The packed routing word: each channel value in its field (the float→fixed shifters
    /// write there directly in the unit).
    #[inline(always)]
    fn packed(&self, q: &[u64; 4]) -> u64 {
        let mut w = 0u64;
        for (c, &v) in q.iter().enumerate() {
            if self.regs.bits[c] > 0 {
                w |= v << self.regs.offset[c];
            }
        }
        w
    }

    /// The code of one box: every stage's operation in pipeline order (the fast mode's
    /// datapath; the same operations the cycle-stepped mode applies stage by stage).
    #[inline]
    pub fn code(&self, b: &Aabb) -> u64 {
        let mut t = Token::new(0, b);
        for s in &self.stages {
            self.apply(s.op, &mut t);
        }
        t.word
    }

    /// Codes of a slice of boxes through the datapath (the fast mode). Boxes are processed in
    /// blocks of [`BLOCK`], stage by stage across the block as the pipeline does, which gives
    /// the host independent work per stage; results equal [`Unit::code`] (tested).
    pub fn codes(&self, boxes: &[Aabb], out: &mut Vec<u64>) {
        out.clear();
        out.resize(boxes.len(), 0);
        self.codes_into(boxes, out);
    }

    /// [`Unit::codes`] into a slice of the same length as `boxes` (extra slots are left).
    pub fn codes_into(&self, boxes: &[Aabb], out: &mut [u64]) {
        let len = boxes.len().min(out.len());
        let out = &mut out[..len];
        let generic = !matches!(
            (&self.regs.size, &self.regs.net),
            (
                SizeUnit::None | SizeUnit::Thresholds { .. } | SizeUnit::Formula { .. },
                Network::Fixed {
                    morton: Some(_),
                    ..
                } | Network::Benes(_)
            )
        );
        if generic {
            for (o, b) in out.iter_mut().zip(boxes) {
                *o = self.code(b);
            }
            return;
        }
        // Network columns as fixed arrays (distance, mask).
        let mut cols = [(0u32, 0u64); 11];
        let mut ncols = 0;
        if let Network::Benes(b) = &self.regs.net {
            ncols = b.columns();
            for (i, c) in cols.iter_mut().enumerate().take(ncols) {
                *c = (b.distance(i), b.masks()[i]);
            }
        }
        // Threshold keys padded to 256 entries so the search index needs no bounds logic.
        let mut keys = [u64::MAX; 256];
        if let SizeUnit::Thresholds { keys: k, .. } = &self.regs.size {
            keys[..k.len()].copy_from_slice(k);
        }
        for (ob, bb) in out.chunks_mut(BLOCK).zip(boxes.chunks(BLOCK)) {
            self.block(bb, ob, &cols[..ncols], &keys);
        }
    }

    /// One block of the fast datapath: positions, d² and threshold search, routing.
    // Several parallel per-channel arrays are indexed by the same channel number.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn block(&self, boxes: &[Aabb], out: &mut [u64], cols: &[(u32, u64)], keys: &[u64; 256]) {
        let r = &self.regs;
        let m = boxes.len();
        let mut q = [[0u64; BLOCK]; 4];
        for a in 0..3 {
            if !r.axis_on[a] {
                continue;
            }
            let (o2, hs, n) = (r.origin2[a], r.half_scale[a], r.bits[a]);
            for (j, b) in boxes.iter().enumerate() {
                let v = ((b.min[a] as f64 + b.max[a] as f64) - o2) * hs;
                q[a][j] = float_to_fixed(v, n);
            }
        }
        if let SizeUnit::Thresholds { bits, .. } = &r.size {
            let mut key = [0u64; BLOCK];
            for (j, b) in boxes.iter().enumerate() {
                let dx = b.max.x as f64 - b.min.x as f64;
                let dy = b.max.y as f64 - b.min.y as f64;
                let dz = b.max.z as f64 - b.min.z as f64;
                key[j] = compare_key((dx * dx + dy * dy) + dz * dz);
            }
            for step in 0..*bits {
                let stride = 1u64 << (bits - 1 - step);
                for j in 0..m {
                    let p = q[3][j];
                    q[3][j] = p + stride * (keys[((p + stride) & 255) as usize] <= key[j]) as u64;
                }
            }
        }
        if let SizeUnit::Formula {
            bits,
            transform,
            diag,
        } = r.size
        {
            for (j, b) in boxes.iter().enumerate() {
                let dx = b.max.x as f64 - b.min.x as f64;
                let dy = b.max.y as f64 - b.min.y as f64;
                let dz = b.max.z as f64 - b.min.z as f64;
                let d = ((dx * dx + dy * dy) + dz * dz).sqrt();
                let v = match transform {
                    SizeTransform::Linear => exp_add(d, bits) / diag,
                    SizeTransform::Sqrt => exp_add((d / diag).sqrt(), bits),
                };
                q[3][j] = float_to_fixed(v, bits);
            }
        }
        if let Network::Fixed { .. } = r.net {
            for j in 0..m {
                out[j] = morton_wires(q[0][j], q[1][j], q[2][j]);
            }
            return;
        }
        let mut w = [0u64; BLOCK];
        for c in 0..4 {
            if r.bits[c] > 0 {
                let off = r.offset[c];
                for j in 0..m {
                    w[j] |= q[c][j] << off;
                }
            }
        }
        for &(d, mask) in cols {
            for x in w.iter_mut() {
                let t = ((*x >> d) ^ *x) & mask;
                *x ^= t | (t << d);
            }
        }
        out.copy_from_slice(&w[..m]);
    }
}

/// Boxes per block of the fast datapath.
pub const BLOCK: usize = 32;

/// The stage list a configuration instantiates.
fn build_stages(r: &Registers, opts: &UnitOptions) -> Vec<Stage> {
    let axes: usize = r.axis_on.iter().filter(|&&o| o).count();
    let size = !matches!(r.size, SizeUnit::None);
    let mut v = Vec::new();
    let st = |name, latency, ii, op, hw: String| Stage {
        name,
        latency,
        ii,
        op,
        hw,
    };
    v.push(st(
        "unpack",
        1,
        1,
        Op::Unpack,
        "192-bit input register".into(),
    ));
    let sz = |s: &str| {
        if size {
            format!(" ∥ size: {s}")
        } else {
            String::new()
        }
    };
    v.push(st(
        "centre",
        FP_LATENCY,
        1,
        Op::Centre,
        format!("{axes}× fp64 add (lo+hi){}", sz("3× fp64 sub (hi−lo)")),
    ));
    v.push(st(
        "offset",
        FP_LATENCY,
        1,
        Op::Offset,
        format!("{axes}× fp64 sub (−2·origin){}", sz("3× fp64 mul (Δ²)")),
    ));
    v.push(st(
        "scale",
        FP_LATENCY,
        1,
        Op::Scale,
        format!("{axes}× fp64 mul (×scale/2){}", sz("1× fp64 add")),
    ));
    v.push(st(
        "float→fixed",
        if size { FP_LATENCY } else { 1 },
        1,
        Op::Fix,
        format!(
            "{axes}× float→fixed+clamp (64-bit field shifter){}",
            sz("1× fp64 add (d²)")
        ),
    ));
    match &r.size {
        SizeUnit::None => {}
        SizeUnit::Thresholds { bits, .. } => match opts.size_search {
            SizeSearch::Binary => {
                const NAMES: [&str; 8] = [
                    "size.search0",
                    "size.search1",
                    "size.search2",
                    "size.search3",
                    "size.search4",
                    "size.search5",
                    "size.search6",
                    "size.search7",
                ];
                for k in 0..*bits {
                    v.push(st(
                        NAMES[k as usize],
                        1,
                        1,
                        Op::SearchStep(k),
                        format!(
                            "63-bit comparator + {}:1 threshold mux",
                            1u32 << k.min(*bits)
                        ),
                    ));
                }
            }
            SizeSearch::Bank => v.push(st(
                "size.bank",
                2,
                1,
                Op::Bank,
                format!("{}× 63-bit comparator + popcount", (1u32 << bits) - 1),
            )),
        },
        SizeUnit::Formula { transform, .. } => {
            let (lat, ii, kind) = if opts.iterative_formula {
                (
                    SQRT_DIV_ITERATIVE_LATENCY,
                    SQRT_DIV_ITERATIVE_LATENCY,
                    "iterative",
                )
            } else {
                (SQRT_DIV_PIPELINED_LATENCY, 1, "pipelined")
            };
            v.push(st(
                "size.sqrt",
                lat,
                ii,
                Op::Sqrt,
                format!("fp64 sqrt ({kind})"),
            ));
            match transform {
                SizeTransform::Linear => {
                    v.push(st(
                        "size.×2^S",
                        1,
                        1,
                        Op::SizeScale,
                        "11-bit exponent adder".into(),
                    ));
                    v.push(st(
                        "size.div",
                        lat,
                        ii,
                        Op::Div,
                        format!("fp64 divide by D ({kind})"),
                    ));
                }
                SizeTransform::Sqrt => {
                    v.push(st(
                        "size.div",
                        lat,
                        ii,
                        Op::Div,
                        format!("fp64 divide by D ({kind})"),
                    ));
                    v.push(st(
                        "size.sqrt2",
                        lat,
                        ii,
                        Op::Sqrt2,
                        format!("fp64 sqrt ({kind})"),
                    ));
                    v.push(st(
                        "size.×2^S",
                        1,
                        1,
                        Op::SizeScale,
                        "11-bit exponent adder".into(),
                    ));
                }
            }
            v.push(st(
                "size.fix",
                1,
                1,
                Op::SizeFix,
                "float→fixed+clamp".into(),
            ));
        }
    }
    match &r.net {
        Network::Fixed { .. } => {}
        Network::Benes(b) => {
            let c = b.columns() as u8;
            let h = c.div_ceil(2);
            v.push(st(
                "route.0",
                1,
                1,
                Op::Route(0, h),
                format!("Beneš columns 0..{h} of {c} ({} lanes)", b.lanes()),
            ));
            v.push(st(
                "route.1",
                1,
                1,
                Op::Route(h, c),
                format!("Beneš columns {h}..{c}"),
            ));
        }
        Network::Crossbar(x) => v.push(st(
            "route",
            1,
            1,
            Op::Route(0, 0),
            format!("{0}×{0} crossbar", x.lanes()),
        )),
    }
    v.push(st(
        "pack",
        1,
        1,
        Op::Pack,
        match r.net {
            Network::Fixed {
                morton: Some(per_axis),
                ..
            } => format!("code register (Morton wires, 3×{per_axis})"),
            Network::Fixed { morton: None, .. } => "code register (fixed wires)".into(),
            _ => "code register".into(),
        },
    ));
    v
}

impl fmt::Display for Unit {
    /// The structure printout: instantiated stages, pruned parts and registers.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let r = &self.regs;
        writeln!(
            f,
            "unit for {} ({}), {} lane(s), depth {} cycles, lane II {}",
            self.spec,
            self.layout,
            self.opts.lanes,
            self.depth(),
            self.lane_ii()
        )?;
        let mut at = 0;
        for s in &self.stages {
            writeln!(
                f,
                "  {:<14} cycles {:>2}..{:<2} lat {:>2} II {:>2}  {}",
                s.name,
                at,
                at + s.latency,
                s.latency,
                s.ii,
                s.hw
            )?;
            at += s.latency;
        }
        let mut pruned = Vec::new();
        for (a, c) in [Channel::X, Channel::Y, Channel::Z].iter().enumerate() {
            if !r.axis_on[a] {
                pruned.push(format!("{c} position lane (0 bits)"));
            }
        }
        if matches!(r.size, SizeUnit::None) {
            pruned.push("size path (0 size bits)".into());
        }
        if matches!(r.net, Network::Fixed { .. }) {
            pruned.push("routing network (fixed layout: wires only)".into());
        }
        if !pruned.is_empty() {
            writeln!(f, "  not instantiated: {}", pruned.join(", "))?;
        }
        write!(
            f,
            "  registers: origin2/scale on {} axes",
            r.axis_on.iter().filter(|&&o| o).count()
        )?;
        match &r.size {
            SizeUnit::None => {}
            SizeUnit::Thresholds { bits, .. } => {
                write!(f, ", {} size thresholds on d² (63-bit)", (1u32 << bits) - 1)?
            }
            SizeUnit::Formula { transform, .. } => {
                write!(f, ", D and S for the {transform} size formula")?
            }
        }
        match &r.net {
            Network::Fixed { .. } => writeln!(f, ", no routing state"),
            Network::Benes(b) => writeln!(
                f,
                ", Beneš {} control bits ({} columns × {} switches)",
                b.control_bits(),
                b.columns(),
                b.switches_per_column()
            ),
            Network::Crossbar(x) => writeln!(
                f,
                ", crossbar {} select bits",
                x.lanes() * x.lanes().trailing_zeros()
            ),
        }
    }
}
