//! The encoder: a resolved layout, its quantiser for one frame and the expansion backend chosen
//! once, at construction. `encode_batch` is the product's hot path: it runs the vectorised
//! pipeline of [`crate::simd`] when the CPU allows, decided once here and reported by
//! [`Encoder::pipeline`]; `encode` and `encode_batch_scalar` are the plain scalar path.

use crate::aabb::Aabb;
use crate::cpu;
use crate::error::Error;
use crate::expand::{Backend, Expander};
use crate::frame::Frame;
use crate::layout::{Layout, LayoutSpec};
use crate::quantize::Quantizer;
use crate::simd::{ExpandPath, Pipeline, QuantizePath, SizePath};

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
    pipeline: Pipeline,
    #[cfg(target_arch = "x86_64")]
    kernel: Option<crate::simd::avx2::Kernel>,
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
        } else if info.avx2
            && crate::expand::magic::Magic::new(&layout).is_some()
            && layout.bit_counts().iter().all(|&b| b <= 31)
        {
            // Measured (Zen 4, pdep forced off, 1M boxes, AVX2 quantise): morton63 3.3 ns/code
            // with the u64x4 spreads against 5.2 with byte tables; morton30 3.0 against 3.2;
            // emc64-sort 4.5 against 5.6.
            (
                Expander::new(Backend::Magic, &layout),
                "magic: pdep is absent or microcoded here and the pattern is regular; AVX2 \
                 u64x4 shift/mask spreads beat byte tables after the AVX2 quantize",
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
        Encoder::assemble(layout, frame, expander, Choice::Auto, reason)
    }

    /// An encoder with a forced backend; an error when that backend cannot serve the layout on
    /// this CPU (magic on an irregular pattern, pdep without BMI2).
    pub fn with_backend(layout: Layout, frame: &Frame, backend: Backend) -> Result<Encoder, Error> {
        let expander = Expander::new(backend, &layout).ok_or(Error::BackendUnavailable(backend))?;
        Ok(Encoder::assemble(
            layout,
            frame,
            expander,
            Choice::Forced,
            "forced by the caller",
        ))
    }

    /// Build the quantiser and pick the batch quantise path (AVX2 when present and every
    /// channel has at most 31 bits).
    fn assemble(
        layout: Layout,
        frame: &Frame,
        expander: Expander,
        choice: Choice,
        reason: &'static str,
    ) -> Encoder {
        let quant = Quantizer::new(&layout, frame);
        let mut e = Encoder {
            pipeline: Pipeline {
                quantize: QuantizePath::Scalar,
                expand: ExpandPath::Scalar(expander.backend()),
                quantize_reason: "no AVX2 on this CPU",
                size: None,
                wide: false,
            },
            quant,
            layout,
            expander,
            choice,
            reason,
            #[cfg(target_arch = "x86_64")]
            kernel: None,
        };
        if cpu::detect().avx2 {
            if e.set_quantize(QuantizePath::Avx2, "AVX2 present").is_err() {
                e.pipeline.quantize_reason =
                    "a channel has 32 bits, beyond the f64x4 to i32x4 truncation";
            }
        } else if !cfg!(target_arch = "x86_64") {
            e.pipeline.quantize_reason = "no SIMD path for this architecture";
        }
        e
    }

    /// Switch the batch quantise path; an error (and no change) when it cannot serve this
    /// layout here.
    fn set_quantize(&mut self, path: QuantizePath, why: &'static str) -> Result<(), Error> {
        match path {
            QuantizePath::Scalar => {
                #[cfg(target_arch = "x86_64")]
                {
                    self.kernel = None;
                }
                self.pipeline = Pipeline {
                    quantize: QuantizePath::Scalar,
                    expand: ExpandPath::Scalar(self.expander.backend()),
                    quantize_reason: why,
                    size: None,
                    wide: false,
                };
                Ok(())
            }
            #[cfg(target_arch = "x86_64")]
            QuantizePath::Avx2 => {
                let info = cpu::detect();
                // AVX-512 serves size channels of up to 6 bits without sqrt or divide (the
                // kernel falls back to the formula beyond); otherwise the per-CPU AVX2 choice.
                let size = if cpu::has_avx512() {
                    SizePath::Avx512Lookup
                } else {
                    SizePath::preferred(&info)
                };
                let kernel = if info.avx2 {
                    crate::simd::avx2::Kernel::new(&self.quant, size)
                } else {
                    None
                };
                // The AVX-512 bit-shuffle expansion is not dispatched: measured on Zen 4
                // (16K boxes in cache, ratio to the streaming baseline) it is slower than
                // scalar pdep after the same quantise step (emc64-var 4.0 against 3.8, morton63
                // 2.6 against 2.4): the vector units are the bottleneck and pdep runs beside
                // them. It stays available through `with_bit_shuffle`.
                let kernel = kernel.ok_or(Error::QuantizeUnavailable(path))?;
                self.kernel = Some(kernel);
                self.refresh_pipeline(why);
                Ok(())
            }
            #[cfg(not(target_arch = "x86_64"))]
            QuantizePath::Avx2 => Err(Error::QuantizeUnavailable(path)),
        }
    }

    /// Describe the AVX2 kernel in use (size and expand paths) in `self.pipeline`.
    #[cfg(target_arch = "x86_64")]
    fn refresh_pipeline(&mut self, why: &'static str) {
        let Some(k) = &self.kernel else {
            return;
        };
        self.pipeline = Pipeline {
            size: k.size_path(),
            quantize: QuantizePath::Avx2,
            expand: if k.bit_shuffle() {
                ExpandPath::BitShuffle512
            } else {
                match self.expander.backend() {
                    Backend::Table => ExpandPath::TableLanes,
                    Backend::Magic => ExpandPath::MagicAvx2,
                    Backend::Pdep => ExpandPath::PdepLanes,
                    Backend::Reference => ExpandPath::ReferenceLanes,
                }
            },
            quantize_reason: why,
            wide: self.expander.backend() == Backend::Pdep && k.wide_pdep(),
        };
    }

    /// The same encoder with the AVX-512 bit-shuffle expansion of the batch forced on or off
    /// (for tests and benchmarks; any backend); an error when the AVX2 path is not in use, or
    /// when `on` and the CPU lacks AVX-512 VBMI/BITALG.
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
    pub fn with_bit_shuffle(mut self, on: bool) -> Result<Encoder, Error> {
        #[cfg(target_arch = "x86_64")]
        if let Some(k) = &mut self.kernel {
            if !k.set_bit_shuffle(on.then(|| self.layout.masks())) {
                return Err(Error::QuantizeUnavailable(QuantizePath::Avx2));
            }
            let why = self.pipeline.quantize_reason;
            self.refresh_pipeline(why);
            return Ok(self);
        }
        let _ = on;
        Err(Error::QuantizeUnavailable(QuantizePath::Avx2))
    }

    /// The same encoder with a forced batch quantise path (for tests and benchmarks); an error
    /// when AVX2 is asked for and the CPU lacks it or a channel has 32 bits.
    pub fn with_quantize(mut self, path: QuantizePath) -> Result<Encoder, Error> {
        self.set_quantize(path, "forced by the caller")?;
        Ok(self)
    }

    /// The same encoder with a forced size path for the AVX2 quantise step (for tests and
    /// benchmarks); an error when the AVX2 path is not in use, or for
    /// [`SizePath::Avx512Lookup`] without AVX-512. Asking for thresholds on a size channel
    /// wider than 8 bits, the AVX-512 lookup on one wider than 6 (or either without a size
    /// channel) keeps the formula, as dispatch would.
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
    pub fn with_size_path(mut self, size: SizePath) -> Result<Encoder, Error> {
        #[cfg(target_arch = "x86_64")]
        if self.kernel.is_some() {
            let shuffle = self.kernel.as_ref().is_some_and(|k| k.bit_shuffle());
            let mut k = crate::simd::avx2::Kernel::new(&self.quant, size)
                .ok_or(Error::QuantizeUnavailable(QuantizePath::Avx2))?;
            k.set_bit_shuffle(shuffle.then(|| self.layout.masks()));
            self.kernel = Some(k);
            let why = self.pipeline.quantize_reason;
            self.refresh_pipeline(why);
            return Ok(self);
        }
        let _ = size;
        Err(Error::QuantizeUnavailable(QuantizePath::Avx2))
    }

    /// What `encode_batch` runs (quantise and expand paths) and why, decided at construction.
    #[inline]
    pub fn pipeline(&self) -> Pipeline {
        self.pipeline
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

    /// Why this expansion backend: one line (see [`Encoder::pipeline`] for the quantise path).
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

    /// [`Encoder::decode`] of a slice of codes into the caller's buffer (same length), the
    /// backend's loop run once for the slice.
    pub fn decode_batch(&self, codes: &[u64], out: &mut [[u64; 4]]) -> Result<(), Error> {
        if codes.len() != out.len() {
            return Err(Error::LengthMismatch(codes.len(), out.len()));
        }
        self.expander.compact_slice(codes, out);
        Ok(())
    }

    /// [`Encoder::expand`] of a slice of channel values into the caller's buffer (same
    /// length), the backend's loop run once for the slice.
    pub fn expand_batch(&self, q: &[[u64; 4]], out: &mut [u64]) -> Result<(), Error> {
        if q.len() != out.len() {
            return Err(Error::LengthMismatch(q.len(), out.len()));
        }
        self.expander.expand_slice(q, out);
        Ok(())
    }

    /// Encode a slice of boxes into the caller's buffer (same length) with the dispatched
    /// pipeline ([`Encoder::pipeline`]). Bit-identical to [`Encoder::encode`] on every box.
    pub fn encode_batch(&self, boxes: &[Aabb], out: &mut [u64]) -> Result<(), Error> {
        if boxes.len() != out.len() {
            return Err(Error::LengthMismatch(boxes.len(), out.len()));
        }
        let done = self.encode_lanes::<false>(boxes, out.as_mut_ptr() as *mut u8);
        for (o, b) in out[done..].iter_mut().zip(&boxes[done..]) {
            *o = self.encode(b);
        }
        Ok(())
    }

    /// [`Encoder::encode_batch`] forced onto the scalar path (one [`Encoder::encode`] per box).
    pub fn encode_batch_scalar(&self, boxes: &[Aabb], out: &mut [u64]) -> Result<(), Error> {
        if boxes.len() != out.len() {
            return Err(Error::LengthMismatch(boxes.len(), out.len()));
        }
        for (o, b) in out.iter_mut().zip(boxes) {
            *o = self.encode(b);
        }
        Ok(())
    }

    /// Encode a slice of boxes into `u32` codes with the dispatched pipeline; an error when the
    /// layout is wider than 32 bits.
    pub fn encode_batch_u32(&self, boxes: &[Aabb], out: &mut [u32]) -> Result<(), Error> {
        if !self.layout.fits_u32() {
            return Err(Error::CodeTooWide(self.layout.len()));
        }
        if boxes.len() != out.len() {
            return Err(Error::LengthMismatch(boxes.len(), out.len()));
        }
        let done = self.encode_lanes::<true>(boxes, out.as_mut_ptr() as *mut u8);
        for (o, b) in out[done..].iter_mut().zip(&boxes[done..]) {
            *o = self.encode(b) as u32;
        }
        Ok(())
    }

    /// [`Encoder::encode_batch_u32`] forced onto the scalar path.
    pub fn encode_batch_u32_scalar(&self, boxes: &[Aabb], out: &mut [u32]) -> Result<(), Error> {
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

    /// Run the SIMD kernel over the leading multiple of four boxes; returns how many it
    /// encoded (0 on the scalar path). `out` holds `boxes.len()` codes (`u32` when `W32`).
    #[inline]
    fn encode_lanes<const W32: bool>(&self, boxes: &[Aabb], out: *mut u8) -> usize {
        #[cfg(target_arch = "x86_64")]
        if let Some(k) = &self.kernel {
            // SAFETY: a kernel is only stored after `cpu::detect()` reported AVX2, and the
            // pdep expander exists only when BMI2 is present; the callers checked that `out`
            // holds `boxes.len()` codes of the width `W32` names.
            return unsafe { k.encode::<W32>(&self.expander, boxes, out) };
        }
        let _ = (boxes, out);
        0
    }
}
