//! The bit-budget sweep of `emc paper` (issue 15 §2): per scene, code lengths from 24 to 64
//! bits, each with the layout `auto:N` picks among that length's family (the candidates of
//! [`crate::auto::candidates`]), built by the plain LBVH with the phases timed apart, costed
//! by SAH, traced, and with the radix passes its codes cost.
#![forbid(unsafe_code)]

use std::fmt::Write as _;

use emc_core::{Frame, LayoutSpec, Normalization};

use super::measure::{trace, MeasureError, Workload};
use crate::auto::{choose, AutoError};
use crate::build::{build_scene, scene_bounds, Builder, Phase, PipelineOptions};
use crate::bvh::refit::CollapseParams;
use crate::scene::Mesh;

/// The code lengths of the sweep.
pub const SWEEP_BITS: [u32; 6] = [24, 32, 40, 48, 56, 64];

/// One code length of the sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct SweepRow {
    /// Code bits.
    pub bits: u32,
    /// The layout auto picked at this length.
    pub spec: LayoutSpec,
    /// Its candidate label (`thr-sqrt`, `emc32-var`, …).
    pub label: String,
    /// Thread-CPU ms of the encode phase (frame and codes).
    pub encode_ms: f64,
    /// Thread-CPU ms of the radix sort.
    pub sort_ms: f64,
    /// Thread-CPU ms of the hierarchy, bounds and collapse.
    pub hierarchy_ms: f64,
    /// Headline SAH (`Ct = Ci = 1`, one primitive per leaf).
    pub sah_headline: f64,
    /// SAH of the collapsed BVH.
    pub sah_collapsed: f64,
    /// Primary rays per thread-CPU second, millions.
    pub primary_mrays: f64,
    /// Key bytes the radix sort ordered by (constant bytes skipped).
    pub sort_passes: u32,
    /// Bits between the lowest and the highest bit in which some codes differ.
    pub varying_bits: u32,
}

/// Errors of the sweep.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    /// The choice failed.
    #[error(transparent)]
    Auto(#[from] AutoError),
    /// A build or trace failed.
    #[error(transparent)]
    Measure(#[from] MeasureError),
    /// The frame could not be made.
    #[error(transparent)]
    Core(#[from] emc_core::Error),
}

/// The layouts of the sweep for these boxes: per length `auto:N`'s pick. Untimed.
pub fn sweep_layouts(
    boxes: &[emc_core::Aabb],
    frame: &Frame,
) -> Result<Vec<(u32, LayoutSpec, String)>, AutoError> {
    SWEEP_BITS
        .iter()
        .map(|&bits| {
            let c = choose(boxes, frame, bits)?;
            Ok((bits, c.spec(), c.candidate().label.to_string()))
        })
        .collect()
}

/// Measure the sweep of one scene: the choices on `untimed` (any number of threads, nothing
/// else running), then each length's build and trace on `pool`; `step(bits, label)` is
/// called once per length as it is done (the progress bar).
pub fn measure_sweep(
    scene: &Mesh,
    work: &Workload,
    repeats: usize,
    pool: &rayon::ThreadPool,
    untimed: &rayon::ThreadPool,
    step: &dyn Fn(u32, &str),
) -> Result<Vec<SweepRow>, SweepError> {
    let layouts = untimed.install(|| -> Result<_, SweepError> {
        let boxes = scene.aabbs();
        let frame = Frame::from_bounds(scene_bounds(&boxes)?, Normalization::CentroidBox)?;
        Ok(sweep_layouts(&boxes, &frame)?)
    })?;
    let threads = pool.current_num_threads();
    let mut rows = Vec::with_capacity(layouts.len());
    for (bits, spec, label) in layouts {
        let out = build_scene(
            scene,
            &PipelineOptions {
                layout: spec.into(),
                builder: Builder::Lbvh,
                threads,
                collapse: CollapseParams::default(),
            },
        )
        .map_err(MeasureError::from)?;
        let r = &out.report;
        let ms = |p: Phase| r.phase(p).cpu_ms;
        let (traced, _, _) = trace(&out.bvh, work, repeats, pool)?;
        rows.push(SweepRow {
            bits,
            spec,
            label,
            encode_ms: ms(Phase::Encode),
            sort_ms: ms(Phase::Sort),
            hierarchy_ms: ms(Phase::Hierarchy) + ms(Phase::Bounds) + ms(Phase::Collapse),
            sah_headline: r.sah_headline,
            sah_collapsed: r.sah_collapsed,
            primary_mrays: traced.primary_mrays(),
            sort_passes: r.sort.passes,
            varying_bits: r.sort.varying_bits,
        });
        step(bits, &rows[rows.len() - 1].label);
    }
    Ok(rows)
}

/// The sweep of one scene as a Markdown table.
pub fn sweep_markdown(name: &str, rows: &[SweepRow]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\n### Bit budget: {name}\n\n| bits | layout (auto:N) | encode ms | sort ms | sort passes (varying bits) | hierarchy ms | SAH | SAH collapsed | primary Mrays/s |\n|---:|---|---:|---:|---:|---:|---:|---:|---:|"
    );
    for r in rows {
        let _ = writeln!(
            s,
            "| {} | {} `{}` | {:.2} | {:.2} | {} ({}) | {:.2} | {:.3} | {:.3} | {:.2} |",
            r.bits,
            r.label,
            r.spec,
            r.encode_ms,
            r.sort_ms,
            r.sort_passes,
            r.varying_bits,
            r.hierarchy_ms,
            r.sah_headline,
            r.sah_collapsed,
            r.primary_mrays
        );
    }
    s
}
