//! The unit's datapath: configuration registers loaded per layout and frame, the named pipeline
//! stages they instantiate (only those the configuration needs), and the stage operations that
//! compute every code — fp64 adders and multipliers, float→fixed, size comparators or the
//! sqrt/divide path, and the routing network — without calling emc-core's encoder.
#![forbid(unsafe_code)]

use core::fmt;
use std::sync::Arc;

use emc_core::{Aabb, Channel, Frame, Layout, LayoutSpec, SizeTransform};

use crate::blocks::{self, Block};
use crate::error::HwError;
use crate::firmware::{is_regular, position_scale, size_thresholds};
use crate::routing::{field_offsets, layout_permutation, Benes, Crossbar, Permutation};

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

/// One named pipeline stage: its timing and the block that describes it once (model
/// behaviour, Verilog, configuration; see [`crate::blocks`]).
#[derive(Clone, Debug)]
pub struct Stage {
    /// Name in the structure printout.
    pub name: &'static str,
    /// Cycles from entry to result.
    pub latency: u32,
    /// Initiation interval (cycles between accepted tokens).
    pub ii: u32,
    /// What hardware the stage instantiates (for the printout).
    pub hw: String,
    /// The block.
    pub block: Arc<dyn Block>,
}

impl Stage {
    fn of(block: Arc<dyn Block>) -> Stage {
        Stage {
            name: block.name(),
            latency: block.latency(),
            ii: block.ii(),
            hw: block.hw(),
            block,
        }
    }
}

/// Largest size-bit count served by threshold registers (the formula path above).
pub const MAX_THRESHOLD_BITS: u32 = 8;

/// Latency of the 3-stage fp64 adder and multiplier (DesignWare-class, 1 GHz at 40 nm).
pub const FP_LATENCY: u32 = 3;
/// Latency (= initiation interval) of an iterative radix-4 fp64 square root or divider.
pub const SQRT_DIV_ITERATIVE_LATENCY: u32 = 28;

/// The intermediate values a token carries down the pipeline.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Token {
    /// Primitive index (for ordering checks).
    pub index: u64,
    pub(crate) lo: [f32; 3],
    pub(crate) hi: [f32; 3],
    pub(crate) c2: [f64; 3],
    pub(crate) dl: [f64; 3],
    pub(crate) acc: f64,
    pub(crate) d2: f64,
    pub(crate) q: [u64; 4],
    pub(crate) sd: f64,
    pub(crate) word: u64,
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
        let stages = build_stages(&regs, opts, &layout);
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

    /// The code of one box: every stage's block in pipeline order (the same evaluations the
    /// cycle-stepped mode applies stage by stage).
    #[inline]
    pub fn code(&self, b: &Aabb) -> u64 {
        let mut t = Token::new(0, b);
        for s in &self.stages {
            s.block.eval(&mut t);
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
        let mut toks = [Token::default(); BLOCK];
        for (ob, bb) in out[..len].chunks_mut(BLOCK).zip(boxes.chunks(BLOCK)) {
            let ts = &mut toks[..bb.len()];
            for (t, b) in ts.iter_mut().zip(bb) {
                t.lo = b.min.to_array();
                t.hi = b.max.to_array();
            }
            for s in &self.stages {
                s.block.eval_all(ts);
            }
            for (o, t) in ob.iter_mut().zip(ts.iter()) {
                *o = t.word;
            }
        }
    }
}

/// Boxes per block of the fast datapath.
pub const BLOCK: usize = 32;

/// The stage list a configuration instantiates: one block per stage, only what the
/// configuration needs.
fn build_stages(r: &Registers, opts: &UnitOptions, layout: &Layout) -> Vec<Stage> {
    let size = !matches!(r.size, SizeUnit::None);
    let need: Vec<usize> = (0..3).filter(|&a| size || r.axis_on[a]).collect();
    let mut v: Vec<Arc<dyn Block>> = vec![
        Arc::new(blocks::Unpack { need }),
        Arc::new(blocks::Centre {
            axis_on: r.axis_on,
            size,
        }),
        Arc::new(blocks::Offset {
            axis_on: r.axis_on,
            size,
            origin2: r.origin2,
        }),
        Arc::new(blocks::Scale {
            axis_on: r.axis_on,
            size,
            half_scale: r.half_scale,
        }),
        Arc::new(blocks::Fix {
            axis_on: r.axis_on,
            size,
            bits: r.bits,
            offset: r.offset,
            programmable: !matches!(r.net, Network::Fixed { .. }),
        }),
    ];
    match &r.size {
        SizeUnit::None => {}
        SizeUnit::Thresholds { bits, keys } => {
            let mut k = Box::new([u64::MAX; 256]);
            k[..keys.len()].copy_from_slice(keys);
            v.push(Arc::new(blocks::Thresholds {
                bits: *bits,
                keys: k,
                bank: opts.size_search == SizeSearch::Bank,
            }));
        }
        SizeUnit::Formula {
            bits,
            transform,
            diag,
        } => {
            let f = |op| -> Arc<dyn Block> {
                Arc::new(blocks::Formula {
                    op,
                    bits: *bits,
                    diag: *diag,
                    stages: crate::cost::recurrence_stages(),
                    iterative: opts.iterative_formula,
                    iterative_latency: SQRT_DIV_ITERATIVE_LATENCY,
                    transform: *transform,
                })
            };
            use blocks::FormulaOp::*;
            let ops: &[blocks::FormulaOp] = match transform {
                SizeTransform::Linear => &[Sqrt, Scale2S, Div, Fix],
                SizeTransform::Sqrt => &[Sqrt, Div, Sqrt2, Scale2S, Fix],
            };
            v.extend(ops.iter().map(|&op| f(op)));
        }
    }
    match &r.net {
        Network::Fixed { .. } => {}
        Network::Benes(b) => {
            let c = b.columns();
            // The network's stages: as many as its critical path needs at the unit's clock.
            let n = crate::cost::benes_stages(b) as usize;
            const NAMES: [&str; 4] = ["route.0", "route.1", "route.2", "route.3"];
            for i in 0..n {
                v.push(Arc::new(blocks::Route {
                    bits: r.bits,
                    offset: r.offset,
                    net: blocks::RouteNet::Benes {
                        net: b.clone(),
                        from: c * i / n,
                        to: c * (i + 1) / n,
                    },
                    stage_name: if n == 1 { "route" } else { NAMES[i.min(3)] },
                }));
            }
        }
        Network::Crossbar(x) => v.push(Arc::new(blocks::Route {
            bits: r.bits,
            offset: r.offset,
            net: blocks::RouteNet::Crossbar(x.clone()),
            stage_name: "route",
        })),
    }
    let (wires, morton) = match &r.net {
        Network::Fixed { src, morton } => (Some(src.clone()), *morton),
        _ => (None, None),
    };
    v.push(Arc::new(blocks::Pack {
        bits: r.bits,
        offset: r.offset,
        len: layout.len(),
        wires,
        morton,
    }));
    v.into_iter().map(Stage::of).collect()
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
