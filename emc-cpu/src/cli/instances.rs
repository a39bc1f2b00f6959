//! `emc compare --instances N`: one mesh instanced `N` times ([`instance_grid`]: rotated,
//! scaled, some mirrored or stretched) as a two-level [`Scene`], beside the same instances in
//! Embree 3 (feature `peers`: top level at LOW with `RTC_SCENE_FLAG_DYNAMIC`, and at MEDIUM),
//! on the protocol's rays over the instances' box: the top level's cold build (every instance
//! added, then the commit), its update (every instance moved, then the commit; and the commit
//! alone), primary and AO Mrays/s, the counts, the memory, and emc's ratios to the best peer of
//! the same run.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use glam::{Affine3A, Vec3};

use super::compare::{CompareArgs, Session, BUILDS};
use super::frames::{median, ms};
use crate::peers::{harness_ao_rays_by, Timing, Tracer};
use crate::scene::{load_with, SceneOptions};
use crate::trace::workload::{instance_grid, primary_rays, Camera, CameraMode, SceneFrame};
use crate::trace::{BuildOptions, Hit, Preset, Ray, Scene};

/// One configuration's figures.
#[derive(Clone, Debug)]
pub struct InstanceRow {
    /// `emc` (LBVH top level) or the Embree top-level quality.
    pub name: &'static str,
    /// Median cold build ms: every instance added, then the commit.
    pub cold_ms: f64,
    /// Median update ms: every instance moved, then the commit.
    pub update_ms: f64,
    /// Median ms of the commit alone after the moves.
    pub commit_ms: f64,
    /// Primary and AO Mrays/s (medians).
    pub mrays: [f64; 2],
    /// Primary hits, AO rays, AO occluded.
    pub counts: [u64; 3],
    /// For a peer: emc's occluded count on this peer's own AO rays (each tracer's AO rays
    /// start at its own primary hits, whose last bits differ between tracers under an
    /// instance's transform; on the same rays the counts must agree).
    pub emc_on_these_rays: Option<u64>,
    /// Bytes of the top level and its instances.
    pub memory: u64,
}

/// The transforms after update `k` (0 = the build's): the grid moved back and forth by a
/// hundredth of the scene's size, so every update moves every instance.
fn placed(base: &[Affine3A], k: usize, step: f32) -> Vec<Affine3A> {
    let d = if k % 2 == 1 { step } else { 0.0 };
    let m = Affine3A::from_translation(Vec3::new(d, 0.5 * d, -d));
    base.iter().map(|b| m * *b).collect()
}

/// Run `--instances` on every scene of `args`.
pub(crate) fn run(args: &CompareArgs, ctx: &Session, n: usize) -> anyhow::Result<()> {
    if n == 0 || n > 100_000_000 {
        bail!("--instances must be in 1..=100000000");
    }
    for spec in &args.scenes {
        let rows = scene_instances(spec, args, ctx, n)?;
        summary(&rows);
    }
    Ok(())
}

fn scene_instances(
    spec: &str,
    args: &CompareArgs,
    ctx: &Session,
    n: usize,
) -> anyhow::Result<Vec<InstanceRow>> {
    let mesh = load_with(spec, &SceneOptions::default().with_prims(args.prims))
        .with_context(|| format!("loading {spec}"))?;
    let (lo, hi) = mesh.vertices.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), v| (lo.min(*v), hi.max(*v)),
    );
    let base = instance_grid(n, lo, hi, 1);
    let step = 0.01 * (hi - lo).max_element() * (n as f32).cbrt();
    let pool = &ctx.pool;
    let threads = ctx.threads;
    let tris: Vec<[Vec3; 3]> = (0..mesh.triangle_count())
        .map(|i| mesh.triangle(i))
        .collect();

    // The instanced mesh, built once with the quality preset (Embree: MEDIUM), not timed
    // with the top level.
    let t0 = Instant::now();
    let blas = pool.install(|| -> anyhow::Result<Arc<Scene>> {
        let mut s = Scene::new();
        s.add_mesh(
            &mesh.vertices,
            &mesh.indices,
            &BuildOptions::preset(Preset::Quality),
        )?;
        s.commit()?;
        Ok(Arc::new(s))
    })?;
    let blas_ms = ms(t0.elapsed());
    println!(
        "\n{spec}: {} triangles instanced {n} times ({} triangles in all), {threads} thread{}; \
         the mesh built once (emc quality preset {blas_ms:.1} ms{})",
        tris.len(),
        tris.len() as u128 * n as u128,
        if threads == 1 { "" } else { "s" },
        if cfg!(feature = "peers") {
            ", Embree MEDIUM"
        } else {
            ""
        },
    );

    // emc: cold builds (a fresh scene each), then updates of the last one.
    let build = || -> anyhow::Result<(Scene, Duration)> {
        let t0 = Instant::now();
        let mut s = Scene::new();
        for m in &base {
            s.add_instance(blas.clone(), *m)?;
        }
        s.commit()?;
        Ok((s, t0.elapsed()))
    };
    drop(pool.install(build)?);
    let mut colds = Vec::with_capacity(BUILDS);
    let mut kept = None;
    for _ in 0..BUILDS {
        drop(kept.take());
        let (s, t) = pool.install(build)?;
        colds.push(ms(t));
        kept = Some(s);
    }
    let Some(mut scene) = kept else {
        bail!("no build was kept")
    };
    let (mut updates, mut commits) = (Vec::new(), Vec::new());
    for k in 1..=BUILDS {
        let xf = placed(&base, k, step);
        let (all, commit) = pool.install(|| -> anyhow::Result<(Duration, Duration)> {
            let t0 = Instant::now();
            for (id, m) in xf.iter().enumerate() {
                scene.set_transform(id as u32, *m)?;
            }
            let c0 = Instant::now();
            scene.commit()?;
            Ok((t0.elapsed(), c0.elapsed()))
        })?;
        updates.push(ms(all));
        commits.push(ms(commit));
    }
    let current = placed(&base, BUILDS, step);
    let mut rows = vec![InstanceRow {
        name: "emc",
        cold_ms: median(colds),
        update_ms: median(updates),
        commit_ms: median(commits),
        mrays: [0.0; 2],
        counts: [0; 3],
        emc_on_these_rays: None,
        memory: scene.memory_bytes() as u64,
    }];
    eprintln!(
        "#   emc            cold {:.1} ms, update {:.1} ms (commit {:.1})",
        rows[0].cold_ms, rows[0].update_ms, rows[0].commit_ms
    );

    #[cfg(feature = "peers")]
    let emesh = crate::peers::embree::Mesh::new(&mesh.vertices, &mesh.indices)?;
    #[cfg(feature = "peers")]
    let (eblas, _) = crate::peers::embree::Instanced::blas(&ctx.device, &emesh)?;
    #[cfg(feature = "peers")]
    let peers = {
        use crate::peers::embree::{Instanced, Quality};
        let mut out = Vec::new();
        for (name, q) in [
            ("embree LOW", Quality::Low),
            ("embree MEDIUM", Quality::Medium),
        ] {
            drop(Instanced::build(&ctx.device, &eblas, &base, q)?);
            let mut colds = Vec::with_capacity(BUILDS);
            let mut kept = None;
            for _ in 0..BUILDS {
                drop(kept.take());
                let (s, cold, _) = Instanced::build(&ctx.device, &eblas, &base, q)?;
                colds.push(ms(cold));
                kept = Some(s);
            }
            let Some(mut s) = kept else {
                bail!("no build was kept")
            };
            let (mut updates, mut commits) = (Vec::new(), Vec::new());
            for k in 1..=BUILDS {
                let (all, commit) = s.update(&placed(&base, k, step))?;
                updates.push(ms(all));
                commits.push(ms(commit));
            }
            let row = InstanceRow {
                name,
                cold_ms: median(colds),
                update_ms: median(updates),
                commit_ms: median(commits),
                mrays: [0.0; 2],
                counts: [0; 3],
                emc_on_these_rays: None,
                memory: s.memory_bytes().max(0) as u64,
            };
            eprintln!(
                "#   {name:<14} cold {:.1} ms, update {:.1} ms (commit {:.1})",
                row.cold_ms, row.update_ms, row.commit_ms
            );
            rows.push(row);
            out.push(s);
        }
        out
    };

    // The protocol's camera over the instances' box; AO rays from each tracer's own hits, on
    // the world-space triangle (the instance's transform applied to the mesh's).
    let b = scene.bounds();
    let frame = SceneFrame::of_box(b.min, b.max);
    let mode = match args.camera.as_deref() {
        Some(c) => c.parse::<CameraMode>().map_err(anyhow::Error::msg)?,
        None => CameraMode::Outside,
    };
    let primary =
        pool.install(|| primary_rays(&Camera::protocol(&frame, mode), args.res, args.res));
    let tri_of = |h: &Hit| {
        let m = &current[h.instance as usize];
        tris[h.prim as usize].map(|v| m.transform_point3(v))
    };
    #[cfg_attr(not(feature = "peers"), allow(unused_mut))] // the peers join it
    let mut tracers: Vec<&dyn Tracer> = vec![&scene];
    #[cfg(feature = "peers")]
    tracers.extend(peers.iter().map(|p| p as &dyn Tracer));
    let mut ao: Vec<Vec<Ray>> = Vec::new();
    for (k, t) in tracers.iter().enumerate() {
        let (hits, _) = t.closest(&primary, threads);
        if let Some(h) = hits.iter().flatten().find(|h| h.instance as usize >= n) {
            bail!("{}: a hit names no instance: {h:?}", rows[k].name);
        }
        let rays = harness_ao_rays_by(&primary, &hits, tri_of, frame.diag);
        let (occ, _) = t.occluded(&rays, threads);
        if k > 0 {
            rows[k].emc_on_these_rays = Some(tracers[0].occluded(&rays, threads).0);
        }
        rows[k].counts = [
            hits.iter().filter(|h| h.is_some()).count() as u64,
            rays.len() as u64,
            occ,
        ];
        ao.push(rays);
    }
    let mut times: Vec<[Vec<Timing>; 2]> = vec![[Vec::new(), Vec::new()]; tracers.len()];
    for _ in 0..args.runs {
        for (k, t) in tracers.iter().enumerate() {
            let (_, tp) = t.closest(&primary, threads);
            let (_, ta) = t.occluded(&ao[k], threads);
            times[k][0].push(tp);
            times[k][1].push(ta);
        }
    }
    for (k, row) in rows.iter_mut().enumerate() {
        let rays = [primary.len(), ao[k].len()];
        for j in 0..2 {
            let s = median(times[k][j].iter().map(|t| t.wall.as_secs_f64()).collect());
            row.mrays[j] = rays[j] as f64 / s / 1e6;
        }
    }
    print_rows(&rows);
    Ok(rows)
}

fn print_rows(rows: &[InstanceRow]) {
    println!(
        "| top level | cold build ms | update ms | commit ms | primary Mrays/s | AO Mrays/s | primary hits | AO rays | AO occluded | memory MB |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        println!(
            "| {} | {:.1} | {:.1} | {:.1} | {:.2} | {:.2} | {} | {} | {} | {:.1} |",
            r.name,
            r.cold_ms,
            r.update_ms,
            r.commit_ms,
            r.mrays[0],
            r.mrays[1],
            r.counts[0],
            r.counts[1],
            r.counts[2],
            r.memory as f64 / 1048576.0
        );
    }
}

/// emc's ratios to the best peer of the run, and the counts against Embree's.
fn summary(rows: &[InstanceRow]) {
    let (emc, peers) = (&rows[0], &rows[1..]);
    if peers.is_empty() {
        println!("peers: not built in; Embree 3 needs `--features peers`");
        return;
    }
    let best = |f: &dyn Fn(&InstanceRow) -> f64, low: bool| {
        peers
            .iter()
            .map(f)
            .fold(if low { f64::INFINITY } else { 0.0 }, |a, b| {
                if low {
                    a.min(b)
                } else {
                    a.max(b)
                }
            })
    };
    println!(
        "emc ÷ best peer: cold build {:.3}, update {:.3}, commit {:.3} (target <= 0.5), primary {:.3}, AO {:.3} (target >= 1.0)",
        emc.cold_ms / best(&|r| r.cold_ms, true),
        emc.update_ms / best(&|r| r.update_ms, true),
        emc.commit_ms / best(&|r| r.commit_ms, true),
        emc.mrays[0] / best(&|r| r.mrays[0], false),
        emc.mrays[1] / best(&|r| r.mrays[1], false),
    );
    for p in peers {
        let d = |a: u64, b: u64| 100.0 * (a as f64 - b as f64).abs() / (b.max(1) as f64);
        println!(
            "counts against {}: primary hits {} vs {} ({:.3}%), AO occluded {} vs {} ({:.3}%)",
            p.name,
            emc.counts[0],
            p.counts[0],
            d(emc.counts[0], p.counts[0]),
            emc.counts[2],
            p.counts[2],
            d(emc.counts[2], p.counts[2]),
        );
        if let Some(same) = p.emc_on_these_rays {
            println!(
                "  on {}'s own AO rays emc finds {} occluded ({:.3}%)",
                p.name,
                same,
                d(same, p.counts[2])
            );
        }
    }
}
