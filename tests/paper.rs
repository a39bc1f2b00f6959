//! `emc paper` end to end on tiny built-in scenes: determinism of SAH costs and layouts for a
//! seed, the files it writes (Markdown, CSV, SVG, PNG), the Pareto marking and the CSV names.

use std::path::PathBuf;
use std::str::FromStr;

use emc_core::LayoutSpec;
use emc_cpu::build::Builder;
use emc_cpu::paper::csv::{RUNS_COLUMNS, SEED_COLUMNS};
use emc_cpu::paper::measure::{all_variants, PaperBuilder, NO_LAYOUT};
use emc_cpu::paper::pareto::pareto_front;
use emc_cpu::paper::{measure_all, run, PaperConfig, PaperError, PaperResults};
use emc_cpu::trace::image::Image;

/// Two small scenes (one where codes matter, one uniform), tiny images, one thread.
fn tiny(out: PathBuf) -> PaperConfig {
    PaperConfig {
        scenes: vec!["builtin:city".into(), "builtin:mixed".into()],
        out,
        threads: 1,
        seed: 7,
        prims: Some(3_000),
        rays: 24 * 24,
        repeats: 1,
        progress: false,
    }
}

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("emc-paper-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// Everything a run must reproduce exactly: per scene and configuration the names, the
/// resolved layout, both SAH costs and the traced counts.
fn fingerprint(r: &PaperResults) -> Vec<String> {
    r.scenes
        .iter()
        .flat_map(|s| {
            s.runs.iter().map(move |x| {
                format!(
                    "{} {} {} {:?} {:e} {:e} {} {} {:e} {:e}",
                    s.name,
                    x.builder.name(),
                    x.layout_name(),
                    x.layout,
                    x.sah_headline,
                    x.sah_collapsed,
                    x.traced.primary_hits,
                    x.traced.ao_occluded,
                    x.traced.node_tests_per_ray,
                    x.traced.tri_tests_per_ray
                )
            })
        })
        .collect()
}

#[test]
fn two_runs_give_identical_costs_and_layouts() {
    // Two threads and scenes big enough to split the parallel phases into several tasks.
    let mut cfg = tiny(temp_dir("det"));
    cfg.threads = 2;
    cfg.prims = Some(40_000);
    let a = measure_all(&cfg).expect("first run");
    let b = measure_all(&cfg).expect("second run");
    assert_eq!(fingerprint(&a), fingerprint(&b));
    // Every configuration is there: 7 layouts × 2 builders + binned SAH, per scene.
    for s in &a.scenes {
        assert_eq!(s.runs.len(), all_variants().len() * 2 + 1);
        // All BVHs of a scene trace the same image: identical hit and occlusion counts.
        let h = (s.runs[0].traced.primary_hits, s.runs[0].traced.ao_occluded);
        for r in &s.runs {
            assert_eq!(
                (r.traced.primary_hits, r.traced.ao_occluded),
                h,
                "{}",
                r.layout_name()
            );
            assert!(r.sah_headline.is_finite() && r.sah_headline >= 1.0);
            assert!(r.sah_collapsed.is_finite() && r.sah_collapsed > 0.0);
        }
        assert!(h.0 > 0, "the camera sees {}", s.name);
    }
    // The seed matters: another seed generates other scenes, hence other costs.
    let mut other = cfg.clone();
    other.seed = 8;
    let c = measure_all(&other).expect("other seed");
    assert_ne!(fingerprint(&a), fingerprint(&c));
}

#[test]
fn writes_markdown_csv_svg_and_png() {
    let dir = temp_dir("files");
    let cfg = tiny(dir.clone());
    let res = run(&cfg).expect("paper run");
    let md = std::fs::read_to_string(dir.join("paper.md")).expect("paper.md");
    for needle in [
        "## 1. The seed's two tables",
        "LBVH (lower quality)",
        "ATRBVH (higher quality)",
        "## 2. What accuracy costs in time",
        "## 3. Example codes",
        "## 4. Shared scenes",
        "## What every bit buys",
        "morton63-cube",
        "★",
    ] {
        assert!(md.contains(needle), "paper.md lacks {needle:?}");
    }
    let csv = std::fs::read_to_string(dir.join("runs.csv")).expect("runs.csv");
    assert_eq!(csv.lines().count(), 1 + 2 * (all_variants().len() * 2 + 1));
    let seed = std::fs::read_to_string(dir.join("seed-tables.csv")).expect("seed-tables.csv");
    assert_eq!(seed.lines().next(), Some(SEED_COLUMNS.join(",").as_str()));
    for stem in ["city", "mixed"] {
        for plot in ["build-vs-sah", "build-vs-time-to-image"] {
            let p = dir.join(format!("{stem}-{plot}.svg"));
            let svg = std::fs::read_to_string(&p).expect("svg");
            assert!(
                svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"),
                "{p:?}"
            );
            assert!(svg.contains("<circle"), "{p:?} has points");
        }
        let p = dir.join(format!("{stem}-bits.svg"));
        let svg = std::fs::read_to_string(&p).expect("bit-budget svg");
        assert!(svg.contains("code bits"), "{p:?} has its axis");
        // Every plot: no two text boxes overlap, and on the Pareto plots every run is labelled.
        let scene = res.scenes.iter().find(|s| s.stem == stem).expect("scene");
        for plot in ["build-vs-sah", "build-vs-time-to-image", "bits"] {
            let p = dir.join(format!("{stem}-{plot}.svg"));
            let svg = std::fs::read_to_string(&p).expect("svg");
            let texts = emc_cpu::paper::plots::text_boxes(&svg);
            assert!(texts.len() > 10, "{p:?}: {} texts", texts.len());
            let clash = emc_cpu::paper::plots::overlapping_texts(&svg);
            assert!(clash.is_empty(), "{p:?}: overlapping labels {clash:?}");
            if plot == "bits" {
                continue;
            }
            for r in &scene.runs {
                let auto = r.variant.is_some_and(|v| v.auto);
                let want = r.layout_name();
                let n = |t: &str| {
                    if auto {
                        t.starts_with("auto = ")
                    } else {
                        t == want
                    }
                };
                let have = texts.iter().filter(|(t, _)| n(t)).count();
                let runs = scene
                    .runs
                    .iter()
                    .filter(|q| {
                        q.variant.is_some_and(|v| v.auto) == auto && q.layout_name() == want
                    })
                    .count();
                assert!(
                    have >= runs,
                    "{p:?}: {want} labelled {have} times, {runs} runs"
                );
            }
        }
        let png = std::fs::File::open(dir.join(format!("{stem}.png"))).expect("png");
        let img = Image::read_png(std::io::BufReader::new(png)).expect("decodes");
        assert_eq!((img.width, img.height), (24, 24));
        assert!(
            img.rgb
                .chunks(3)
                .any(|c| c != emc_cpu::trace::image::BACKGROUND),
            "{stem}.png shows the scene"
        );
    }
    assert_eq!(res.files.len(), 3 + 2 * 4);
    for f in &res.files {
        assert!(f.is_file(), "{f:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn pareto_marking_on_a_hand_made_example() {
    let pts = [
        (1.0, 5.0),      // cheapest build: front
        (2.0, 3.0),      // front
        (3.0, 4.0),      // dominated by (2, 3)
        (4.0, 1.0),      // best cost: front
        (2.0, 3.0),      // equal to a front point: front too
        (5.0, 5.0),      // dominated by everything
        (1.0, 6.0),      // same build as (1, 5) but worse cost: dominated
        (f64::NAN, 0.0), // unmeasured: never on the front
    ];
    assert_eq!(
        pareto_front(&pts),
        vec![true, true, false, true, true, false, false, false]
    );
    assert_eq!(pareto_front(&[]), Vec::<bool>::new());
    assert_eq!(pareto_front(&[(3.0, 3.0)]), vec![true]);
}

#[test]
fn csv_uses_the_shared_layout_and_builder_names() {
    let cfg = tiny(temp_dir("csv"));
    let res = measure_all(&cfg).expect("run");
    let csv = emc_cpu::paper::csv::runs_csv(&res);
    let mut lines = csv.lines();
    let head: Vec<&str> = lines.next().expect("header").split(',').collect();
    assert_eq!(head, RUNS_COLUMNS.to_vec());
    let col = |n: &str| head.iter().position(|h| *h == n).expect(n);
    let (b, l) = (col("builder"), col("layout"));
    let mut layouts = std::collections::BTreeSet::new();
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        assert_eq!(f.len(), head.len(), "{line}");
        match f[b] {
            "atrbvh" => {}
            name => {
                let parsed = Builder::from_str(name).expect("a pipeline builder name");
                assert_eq!(parsed.name(), name);
            }
        }
        let layout = f[l];
        layouts.insert(layout.to_string());
        if f[b] == PaperBuilder::BinnedSah.name() {
            assert_eq!(layout, NO_LAYOUT);
        } else if layout == "auto" {
            assert!(emc_cpu::auto::LayoutChoice::from_str(layout)
                .expect("auto")
                .is_auto());
        } else if let Some(base) = layout.strip_suffix("-cube") {
            assert_eq!(
                LayoutSpec::from_str(base).expect("layout").to_string(),
                base
            );
        } else {
            assert_eq!(
                LayoutSpec::from_str(layout).expect("layout").to_string(),
                layout
            );
        }
    }
    let expected: std::collections::BTreeSet<String> = [
        "morton30",
        "morton63",
        "emc32-var",
        "emc64-sort",
        "emc64-var",
        "emc64-var-nosize",
        "morton63-cube",
        "auto",
        "none",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    assert_eq!(layouts, expected);
}

#[test]
fn bad_configurations_are_refused() {
    let mut cfg = tiny(temp_dir("bad"));
    cfg.threads = 0;
    assert!(matches!(measure_all(&cfg), Err(PaperError::ZeroThreads)));
    let mut cfg = tiny(temp_dir("bad"));
    cfg.rays = 0;
    assert!(matches!(measure_all(&cfg), Err(PaperError::ZeroRays)));
    let mut cfg = tiny(temp_dir("bad"));
    cfg.scenes.clear();
    assert!(matches!(measure_all(&cfg), Err(PaperError::NoScenes)));
    let mut cfg = tiny(temp_dir("bad"));
    cfg.scenes = vec!["builtin:no-such-scene".into()];
    assert!(matches!(measure_all(&cfg), Err(PaperError::Mesh { .. })));
    let mut cfg = tiny(temp_dir("bad"));
    cfg.scenes = vec!["builtin:city".into(), "builtin:city".into()];
    assert!(matches!(measure_all(&cfg), Err(PaperError::Duplicate(_))));
}

/// The build issue's claim on a shared scene, through the paper's own build path: `emc64-var`
/// lowers the LBVH SAH (both figures) versus `morton63`. Skips when the scenes are absent.
#[test]
fn emc64_var_lowers_lbvh_sah_on_a_shared_scene() {
    let name = "sionna-san-francisco";
    if emc_cpu::scene::shared_scene_path(name).is_none() {
        eprintln!("skipping: shared scene {name} not found (set EMC_SHARED_DIR)");
        return;
    }
    let scene = emc_cpu::scene::load(name).expect("loads");
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .expect("pool");
    let build = |spec| {
        emc_cpu::paper::measure::build(
            &scene,
            PaperBuilder::Lbvh,
            &emc_cpu::paper::measure::Variant::plain(spec),
            &pool,
        )
        .expect("builds")
    };
    let (m, v) = (build(LayoutSpec::Morton63), build(LayoutSpec::Emc64Var));
    eprintln!(
        "{name}: LBVH SAH morton63 {:.3} / {:.3}, emc64-var {:.3} / {:.3}",
        m.sah_headline, m.sah_collapsed, v.sah_headline, v.sah_collapsed
    );
    assert!(v.sah_headline < m.sah_headline);
    assert!(v.sah_collapsed < m.sah_collapsed);
}
