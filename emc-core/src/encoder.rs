//! The encoder: a resolved layout, its quantiser for one frame and the expansion backend chosen
//! once, at construction. `encode_batch` is the product's hot path.

use crate::aabb::Aabb;
use crate::cpu;
use crate::error::Error;
use crate::expand::{Backend, Expander};
use crate::frame::Frame;
use crate::layout::{Layout, LayoutSpec};
use crate::quantize::Quantizer;

/// How an encoder's backend was chosen.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Choice {
    /// Picked by [`Encoder::new`] from the CPU and the layout.
    Auto,
    /// Forced by the caller.
    Forced,
}

/// Encodes primitive boxes of one frame into codes of one layout.
#[derive(Clone, Debug)]
pub struct Encoder {
    layout: Layout,
    quant: Quantizer,
    expander: Expander,
    choice: Choice,
    reason: &'static str,
}

impl Encoder {
    /// An encoder for a named layout in a frame, with the backend dispatch picks for this CPU.
    pub fn new(spec: &LayoutSpec, frame: &Frame) -> Encoder {
        Encoder::for_layout(spec.resolve(frame.extent()), frame)
    }

    /// An encoder for a concrete layout, with the backend dispatch picks for this CPU.
    pub fn for_layout(layout: Layout, frame: &Frame) -> Encoder {
        let info = cpu::detect();
        let (expander, reason) = if info.fast_pdep() {
            (
                Expander::new(Backend::Pdep, &layout),
                "pdep: BMI2 present and pdep is a fast single instruction on this CPU",
            )
        } else if info.bmi2 {
            (
                Expander::new(Backend::Table, &layout),
                "table: BMI2 present but pdep is microcoded on AMD/Hygon before family 0x19; \
                 byte tables are the fastest general expander there",
            )
        } else {
            (
                Expander::new(Backend::Table, &layout),
                "table: no BMI2 on this CPU; byte tables are the fastest general expander",
            )
        };
        // Both branches ask for backends that always build on the CPU they were picked for.
        let expander =
            expander.unwrap_or_else(|| Expander::Table(crate::expand::table::Table::new(&layout)));
        Encoder {
            quant: Quantizer::new(&layout, frame),
            layout,
            expander,
            choice: Choice::Auto,
            reason,
        }
    }

    /// An encoder with a forced backend; an error when that backend cannot serve the layout on
    /// this CPU (magic on an irregular pattern, pdep without BMI2).
    pub fn with_backend(layout: Layout, frame: &Frame, backend: Backend) -> Result<Encoder, Error> {
        let expander = Expander::new(backend, &layout).ok_or(Error::BackendUnavailable(backend))?;
        Ok(Encoder {
            quant: Quantizer::new(&layout, frame),
            layout,
            expander,
            choice: Choice::Forced,
            reason: "forced by the caller",
        })
    }

    /// The concrete layout.
    #[inline]
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// The quantiser (per-frame constants).
    #[inline]
    pub fn quantizer(&self) -> &Quantizer {
        &self.quant
    }

    /// The expansion backend in use.
    #[inline]
    pub fn backend(&self) -> Backend {
        self.expander.backend()
    }

    /// The expander in use.
    #[inline]
    pub fn expander(&self) -> &Expander {
        &self.expander
    }

    /// Whether the backend was picked automatically or forced.
    #[inline]
    pub fn choice(&self) -> Choice {
        self.choice
    }

    /// Why this backend: one line.
    #[inline]
    pub fn reason(&self) -> &'static str {
        self.reason
    }

    /// The code of one primitive box.
    #[inline]
    pub fn encode(&self, b: &Aabb) -> u64 {
        self.expander.expand(self.quant.quantize(b))
    }

    /// Interleave channel values with this encoder's backend.
    #[inline]
    pub fn expand(&self, q: [u64; 4]) -> u64 {
        self.expander.expand(q)
    }

    /// Split a code into its channel values (x, y, z, s).
    #[inline]
    pub fn decode(&self, code: u64) -> [u64; 4] {
        self.expander.compact(code)
    }

    /// Encode a slice of boxes into the caller's buffer (same length).
    pub fn encode_batch(&self, boxes: &[Aabb], out: &mut [u64]) -> Result<(), Error> {
        if boxes.len() != out.len() {
            return Err(Error::LengthMismatch(boxes.len(), out.len()));
        }
        for (o, b) in out.iter_mut().zip(boxes) {
            *o = self.encode(b);
        }
        Ok(())
    }

    /// Encode a slice of boxes into `u32` codes; an error when the layout is wider than 32 bits.
    pub fn encode_batch_u32(&self, boxes: &[Aabb], out: &mut [u32]) -> Result<(), Error> {
        if !self.layout.fits_u32() {
            return Err(Error::CodeTooWide(self.layout.len()));
        }
        if boxes.len() != out.len() {
            return Err(Error::LengthMismatch(boxes.len(), out.len()));
        }
        for (o, b) in out.iter_mut().zip(boxes) {
            *o = self.encode(b) as u32;
        }
        Ok(())
    }
}
