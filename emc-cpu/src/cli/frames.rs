//! `emc compare --frames N`: an animated scene (`builtin:wave`) frame by frame, as a renderer
//! of dynamic geometry runs it: per frame emc's `Accel::refit` and `Accel::rebuild` (fast
//! preset) beside Embree's commit of the same moved vertices with the geometry at
//! `RTC_BUILD_QUALITY_REFIT` and at LOW (feature `peers`), then the frame's primary rays
//! through every structure, so the trace speed of the refitted tree against a rebuilt one
//! shows when a rebuild pays. Wall times of one update per frame; medians over the frames.

use std::io::Write;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use glam::Vec3;

use super::compare::{CompareArgs, Session};
use crate::peers::{Protocol, Tracer};
use crate::scene::builtin::{self, ANIMATED_NAMES};
use crate::scene::{load_with, SceneOptions};
use crate::trace::workload::CameraMode;
use crate::trace::{Accel, BuildOptions, Preset};

/// The header of `--frames --csv FILE`.
pub const FRAMES_CSV_HEADER: &str = "scene,triangles,threads,frame,refit_ms,rebuild_ms,\
embree_refit_ms,embree_low_ms,mrays_refit,mrays_rebuild,mrays_embree_refit,mrays_embree_low";

/// One frame's figures (`None` where a peer is not built in).
#[derive(Clone, Copy, Debug, Default)]
pub struct FrameRow {
    /// Frame number (1 = the first move after the build at frame 0).
    pub frame: u32,
    /// `Accel::refit` wall ms.
    pub refit_ms: f64,
    /// `Accel::rebuild` wall ms.
    pub rebuild_ms: f64,
    /// Embree commit with the geometry at REFIT quality.
    pub embree_refit_ms: Option<f64>,
    /// Embree commit with the geometry at LOW quality.
    pub embree_low_ms: Option<f64>,
    /// Primary Mrays/s: emc refitted, emc rebuilt, Embree REFIT, Embree LOW.
    pub mrays: [Option<f64>; 4],
    /// Primary hits of the refitted and the rebuilt tree (equal: both are exact).
    pub hits: [u64; 2],
}

/// Milliseconds of `d`.
pub(crate) fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// Median of `v` (NaN when empty).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

fn cell(x: Option<f64>, digits: usize) -> String {
    x.map_or("-".to_string(), |v| format!("{v:.digits$}"))
}

/// Run `--frames` on every scene of `args`.
pub(crate) fn run(args: &CompareArgs, ctx: &Session, frames: u32) -> anyhow::Result<()> {
    if frames == 0 || frames > 100_000 {
        bail!("--frames must be in 1..=100000");
    }
    let mut csv = match &args.csv {
        Some(p) => {
            let mut f = std::io::BufWriter::new(
                std::fs::File::create(p).with_context(|| format!("creating {p}"))?,
            );
            writeln!(f, "{FRAMES_CSV_HEADER}").with_context(|| format!("writing {p}"))?;
            Some((p, f))
        }
        None => None,
    };
    for spec in &args.scenes {
        let name = spec.strip_prefix("builtin:").unwrap_or("");
        if !ANIMATED_NAMES.contains(&name) {
            bail!(
                "--frames needs an animated scene (builtin:{}); `{spec}` is not one",
                ANIMATED_NAMES.join(", builtin:")
            );
        }
        let rows = scene_frames(spec, args, ctx, frames)?;
        if let Some((p, f)) = &mut csv {
            for r in &rows {
                let o = |x: Option<f64>| x.map_or(String::new(), |v| format!("{v:.4}"));
                writeln!(
                    f,
                    "{spec},{},{},{},{:.4},{:.4},{},{},{},{},{},{}",
                    2 * (side(args) - 1) * (side(args) - 1),
                    args.threads,
                    r.frame,
                    r.refit_ms,
                    r.rebuild_ms,
                    o(r.embree_refit_ms),
                    o(r.embree_low_ms),
                    o(r.mrays[0]),
                    o(r.mrays[1]),
                    o(r.mrays[2]),
                    o(r.mrays[3]),
                )
                .with_context(|| format!("writing {p}"))?;
            }
            f.flush().with_context(|| format!("writing {p}"))?;
        }
    }
    Ok(())
}

fn scene_opts(args: &CompareArgs, frame: u32) -> SceneOptions {
    SceneOptions::default()
        .with_prims(args.prims)
        .with_frame(frame)
}

/// Grid side of the wave for `--prims`.
fn side(args: &CompareArgs) -> usize {
    builtin::wave_side(args.prims.unwrap_or(builtin::DEFAULT_PRIMS))
}

/// The frames of one animated scene: build everything at frame 0 (untimed), then per frame
/// move the vertices and time each update, then trace the frame's primary rays.
fn scene_frames(
    spec: &str,
    args: &CompareArgs,
    ctx: &Session,
    frames: u32,
) -> anyhow::Result<Vec<FrameRow>> {
    let s0 = load_with(spec, &scene_opts(args, 0)).with_context(|| format!("loading {spec}"))?;
    let ntris = s0.triangle_count();
    let mode = match args.camera.as_deref() {
        Some(c) => c.parse::<CameraMode>().map_err(anyhow::Error::msg)?,
        None => CameraMode::for_scene(&s0.name),
    };
    let opts = BuildOptions::preset(Preset::Fast);
    let pool = &ctx.pool;
    let mut refitted = pool.install(|| Accel::build(&s0.vertices, &s0.indices, &opts))?;
    let mut rebuilt = pool.install(|| Accel::build(&s0.vertices, &s0.indices, &opts))?;
    #[cfg(feature = "peers")]
    let mut embree = {
        use crate::peers::embree::{Animated, Update};
        let (r, _) = Animated::build(&ctx.device, &s0.vertices, &s0.indices, Update::Refit)?;
        let (l, _) = Animated::build(&ctx.device, &s0.vertices, &s0.indices, Update::Low)?;
        (r, l)
    };
    println!(
        "\n{spec}: {ntris} triangles, {frames} frames after frame 0, {} thread{}, camera {mode:?}, \
         primary rays {}x{} per frame; emc fast preset refitted and rebuilt{}",
        ctx.threads,
        if ctx.threads == 1 { "" } else { "s" },
        args.res,
        args.res,
        if cfg!(feature = "peers") {
            "; Embree 3 dynamic scenes (geometry at REFIT, and at LOW)"
        } else {
            "; peers not built in (--features peers)"
        }
    );
    println!(
        "| frame | emc refit ms | emc rebuild ms | embree REFIT ms | embree LOW ms | primary Mrays/s: emc refitted | emc rebuilt | embree REFIT | embree LOW | refitted ÷ rebuilt |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut rows = Vec::with_capacity(frames as usize);
    for frame in 1..=frames {
        let v = builtin::wave_vertices(
            builtin::wave_side(args.prims.unwrap_or(builtin::DEFAULT_PRIMS)),
            frame,
        );
        if v.len() != s0.vertices.len() {
            bail!(
                "{spec}: frame {frame} has {} vertices, frame 0 {}",
                v.len(),
                s0.vertices.len()
            );
        }
        let mut row = FrameRow {
            frame,
            ..FrameRow::default()
        };
        let t = Instant::now();
        pool.install(|| refitted.refit(&v))?;
        row.refit_ms = ms(t.elapsed());
        let t = Instant::now();
        pool.install(|| rebuilt.rebuild(&v))?;
        row.rebuild_ms = ms(t.elapsed());
        #[cfg(feature = "peers")]
        {
            row.embree_refit_ms = Some(ms(embree.0.update(&v)?));
            row.embree_low_ms = Some(ms(embree.1.update(&v)?));
        }
        let tris: Vec<[Vec3; 3]> = s0
            .indices
            .iter()
            .map(|t| t.map(|i| v[i as usize]))
            .collect();
        let protocol = pool.install(|| Protocol::new(tris, mode, args.res));
        let rays = &protocol.primary;
        let mrays = |t: &dyn Tracer| -> (f64, u64) {
            let (hits, time) = t.closest(rays, ctx.threads);
            (
                rays.len() as f64 / time.wall.as_secs_f64() / 1e6,
                hits.iter().filter(|h| h.is_some()).count() as u64,
            )
        };
        let (m0, h0) = mrays(&refitted);
        let (m1, h1) = mrays(&rebuilt);
        row.mrays[0] = Some(m0);
        row.mrays[1] = Some(m1);
        row.hits = [h0, h1];
        if h0 != h1 {
            bail!(
                "{spec} frame {frame}: the refitted tree hits {h0} primary rays, the rebuilt {h1}"
            );
        }
        #[cfg(feature = "peers")]
        {
            row.mrays[2] = Some(mrays(&embree.0).0);
            row.mrays[3] = Some(mrays(&embree.1).0);
        }
        println!(
            "| {frame} | {:.2} | {:.2} | {} | {} | {:.2} | {:.2} | {} | {} | {:.3} |",
            row.refit_ms,
            row.rebuild_ms,
            cell(row.embree_refit_ms, 2),
            cell(row.embree_low_ms, 2),
            m0,
            m1,
            cell(row.mrays[2], 2),
            cell(row.mrays[3], 2),
            m0 / m1
        );
        rows.push(row);
    }
    summary(&rows);
    Ok(rows)
}

/// Medians over the frames, the two targets, and where the refitted tree's trace
/// speed falls below 90% of a rebuilt one's.
fn summary(rows: &[FrameRow]) {
    let med = |f: &dyn Fn(&FrameRow) -> Option<f64>| {
        let v: Vec<f64> = rows.iter().filter_map(f).collect();
        (!v.is_empty()).then(|| median(v))
    };
    let refit = med(&|r| Some(r.refit_ms)).unwrap_or(f64::NAN);
    let rebuild = med(&|r| Some(r.rebuild_ms)).unwrap_or(f64::NAN);
    println!(
        "medians over {} frames: emc refit {refit:.2} ms, rebuild {rebuild:.2} ms",
        rows.len()
    );
    if let (Some(er), Some(el)) = (med(&|r| r.embree_refit_ms), med(&|r| r.embree_low_ms)) {
        println!(
            "  embree REFIT commit {er:.2} ms, LOW re-commit {el:.2} ms; emc refit ÷ embree REFIT = {:.3} (target <= 0.5), emc rebuild ÷ embree LOW = {:.3} (target <= 0.25)",
            refit / er,
            rebuild / el
        );
    }
    match rows
        .iter()
        .find(|r| r.mrays[0].zip(r.mrays[1]).is_some_and(|(a, b)| a < 0.9 * b))
    {
        Some(r) => println!(
            "  the refitted tree first traces below 90% of a rebuilt one at frame {}: rebuild from then on (or every few frames)",
            r.frame
        ),
        None => println!("  the refitted tree traces at >= 90% of a rebuilt one on every frame"),
    }
}
