//! Scenes: the triangle soups that every builder, encoder and tracer of emc-cpu consumes.
//! A [`Mesh`] comes from an OBJ file (the `obj` module, feature `obj`), a zstd-compressed
//! OBJ, a shared scene named by its stem, or a deterministic procedural generator
//! ([`builtin`], always there); [`load`] picks by the spec.
#![forbid(unsafe_code)]

pub mod builtin;
#[cfg(feature = "obj")]
pub mod obj;

use std::path::{Path, PathBuf};

use emc_core::{Aabb, SceneBounds};
use glam::Vec3;
use rayon::prelude::*;

/// The shared scenes with their triangle counts, as the shared scenes' README lists them
/// (sorted by triangle count). Files are `NAME.obj` or `NAME.obj.zst` in
/// [`shared_scenes_dir`].
pub const SHARED_SCENES: [(&str, usize); 10] = [
    ("spot", 5_856),
    ("sionna-etoile", 13_098),
    ("sionna-munich", 38_936),
    ("torcs-spring", 62_875),
    ("stanford-bunny", 69_451),
    ("sionna-san-francisco", 268_041),
    ("pbrt-bathroom", 447_123),
    ("stanford-dragon", 871_414),
    ("pbrt-crown", 3_540_214),
    ("san-miguel-pbrtv3", 9_384_746),
];

/// Everything that can go wrong when loading or generating a scene.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SceneError {
    /// The file does not exist or cannot be opened.
    #[error("cannot open scene file {path}: {source}")]
    Open {
        /// The file asked for.
        path: PathBuf,
        /// What the operating system said.
        source: std::io::Error,
    },
    /// Reading or decompressing failed part-way.
    #[error("cannot read scene file {path}: {source}")]
    Read {
        /// The file being read.
        path: PathBuf,
        /// What the reader or the zstd decoder said.
        source: std::io::Error,
    },
    /// Writing a scene file failed.
    #[error("cannot write scene file {path}: {source}")]
    Write {
        /// The file being written.
        path: PathBuf,
        /// What the writer or the zstd encoder said.
        source: std::io::Error,
    },
    /// A malformed line (bad number, too few fields, index 0 or out of range, bad UTF-8).
    #[error("{path}:{line}: {message}")]
    Malformed {
        /// The file being parsed.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with the line.
        message: String,
    },
    /// `tobj` refused the file for a reason the line check did not see.
    #[cfg(feature = "obj")]
    #[error("{path}: OBJ parser error: {source}")]
    Obj {
        /// The file being parsed.
        path: PathBuf,
        /// The `tobj` error.
        source: tobj::LoadError,
    },
    /// A scene file was asked for, but this build reads none (emc-cpu without `obj`).
    #[error("{path}: reading OBJ files needs emc-cpu's `obj` feature")]
    NoObjSupport {
        /// The file asked for.
        path: PathBuf,
    },
    /// The file holds no triangle at all (empty, only vertices, only comments...).
    #[error("{path}: no triangles in the scene")]
    NoTriangles {
        /// The file (or built-in spec) that was empty.
        path: PathBuf,
    },
    /// Every triangle had a NaN or infinite vertex and was dropped.
    #[error("{path}: all {dropped} triangles have a non-finite vertex")]
    AllNonFinite {
        /// The file (or built-in spec).
        path: PathBuf,
        /// How many triangles were dropped.
        dropped: usize,
    },
    /// More than `u32::MAX` vertices (indices are 32-bit).
    #[error("{path}: too many vertices ({count}) for 32-bit indices")]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Vertex count found.
        count: usize,
    },
    /// `builtin:NAME` with a name that is not a built-in scene.
    #[error(
        "unknown built-in scene `{0}` (known: {known}, {animated}, {hard})",
        known = builtin::NAMES.join(", "),
        animated = builtin::ANIMATED_NAMES.join(", "),
        hard = builtin::HARD_NAMES.join(", ")
    )]
    UnknownBuiltin(String),
    /// A bare scene name that is not a file and not found in the shared scenes directory.
    #[error("scene `{name}` is neither a file nor a shared scene ({where_})")]
    UnknownScene {
        /// The spec as given.
        name: String,
        /// Where the shared scenes were looked for.
        where_: String,
    },
    /// `prims` of 0 (a built-in scene needs at least one triangle).
    #[error("built-in scene `{0}`: --prims must be at least 1")]
    ZeroPrims(String),
}

/// An indexed triangle mesh in `f32`.
///
/// Invariants after [`load`]: at least one triangle, every index `< vertices.len()`, every
/// vertex used by a triangle is finite.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// A short name: the file stem or `builtin:NAME`.
    pub name: String,
    /// Vertex positions.
    pub vertices: Vec<Vec3>,
    /// Triangles as three vertex indices.
    pub indices: Vec<[u32; 3]>,
    /// Triangles dropped at load time because a vertex had a NaN or infinite coordinate.
    pub dropped_nonfinite: usize,
}

impl Mesh {
    /// Number of triangles.
    #[inline]
    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }

    /// The three vertices of triangle `i` (panics when `i` is out of range).
    #[inline]
    pub fn triangle(&self, i: usize) -> [Vec3; 3] {
        let [a, b, c] = self.indices[i];
        [
            self.vertices[a as usize],
            self.vertices[b as usize],
            self.vertices[c as usize],
        ]
    }

    /// Primitive boxes, one per triangle, computed in parallel by [`crate::aabbs`] on the
    /// fastest path this CPU has (bit-identical to the scalar path).
    pub fn aabbs(&self) -> Vec<Aabb> {
        let mut out = vec![Aabb::EMPTY; self.indices.len()];
        crate::aabbs::triangle_aabbs(&self.vertices, &self.indices, &mut out);
        out
    }

    /// The box of all triangles (the union of their boxes; unreferenced vertices ignored).
    /// [`Aabb::EMPTY`] for a scene without triangles.
    pub fn bounds(&self) -> Aabb {
        self.indices
            .par_chunks(1 << 14)
            .map(|chunk| {
                let mut b = Aabb::EMPTY;
                for t in chunk {
                    for &v in t {
                        b.grow(self.vertices[v as usize]);
                    }
                }
                b
            })
            .reduce(|| Aabb::EMPTY, |a, b| a.union(&b))
    }

    /// The frame bounds (centroid box, primitive box, count) of the triangle boxes, reduced in
    /// parallel; feed it to [`emc_core::Frame::from_bounds`].
    pub fn scene_bounds(&self, boxes: &[Aabb]) -> Result<SceneBounds, emc_core::Error> {
        const CHUNK: usize = 1 << 14;
        boxes
            .par_chunks(CHUNK)
            .enumerate()
            .map(|(k, c)| SceneBounds::of(c, k * CHUNK))
            .try_reduce(|| SceneBounds::EMPTY, |a, b| Ok(a.merge(&b)))
    }
}

/// Options of [`load_with`]: they only affect `builtin:` scenes.
///
/// ```
/// let opts = emc_cpu::scene::SceneOptions::default().with_prims(5000).with_seed(7);
/// assert_eq!((opts.prims, opts.seed), (Some(5000), 7));
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub struct SceneOptions {
    /// Approximate triangle count of a built-in scene (each generator documents how it rounds);
    /// `None` takes the generator's default size.
    pub prims: Option<usize>,
    /// Seed of the built-in generators (same seed, same scene, bit for bit).
    pub seed: u64,
    /// Frame of an animated built-in scene (`builtin:wave`); the others ignore it.
    pub frame: u32,
}

impl Default for SceneOptions {
    fn default() -> Self {
        SceneOptions {
            prims: None,
            seed: builtin::DEFAULT_SEED,
            frame: 0,
        }
    }
}

impl SceneOptions {
    /// With about this many triangles in a built-in scene (`None`: the generator's default).
    #[inline]
    pub fn with_prims(mut self, prims: impl Into<Option<usize>>) -> SceneOptions {
        self.prims = prims.into();
        self
    }

    /// With this seed of the built-in generators.
    #[inline]
    pub fn with_seed(mut self, seed: u64) -> SceneOptions {
        self.seed = seed;
        self
    }

    /// At this frame of an animated built-in scene.
    #[inline]
    pub fn with_frame(mut self, frame: u32) -> SceneOptions {
        self.frame = frame;
        self
    }
}

/// Load a scene with default options. See [`load_with`] for the spec syntax.
pub fn load(spec: &str) -> Result<Mesh, SceneError> {
    load_with(spec, &SceneOptions::default())
}

/// Load a scene.
///
/// `spec` is one of:
/// - `builtin:NAME`: a procedural scene of [`builtin::NAMES`], sized by `opts.prims` and seeded
///   by `opts.seed`, or an animated one of [`builtin::ANIMATED_NAMES`] at `opts.frame`;
/// - a path to an `.obj` or `.obj.zst` file (if the file exists, or the spec ends in one of
///   those extensions);
/// - a bare shared-scene name such as `pbrt-bathroom`, looked up by [`shared_scene_path`].
pub fn load_with(spec: &str, opts: &SceneOptions) -> Result<Mesh, SceneError> {
    #[cfg(feature = "obj")]
    fn load_file(path: &Path) -> Result<Mesh, SceneError> {
        obj::load_obj_file(path)
    }
    #[cfg(not(feature = "obj"))]
    fn load_file(path: &Path) -> Result<Mesh, SceneError> {
        Err(SceneError::NoObjSupport {
            path: path.to_path_buf(),
        })
    }
    if let Some(name) = spec.strip_prefix("builtin:") {
        return builtin::generate(name, opts);
    }
    let path = Path::new(spec);
    let looks_like_file = spec.ends_with(".obj") || spec.ends_with(".zst") || spec.contains('/');
    if path.exists() || looks_like_file {
        return load_file(path);
    }
    match shared_scene_path(spec) {
        Some(p) => load_file(&p),
        None => Err(SceneError::UnknownScene {
            name: spec.to_string(),
            where_: match shared_scenes_dir() {
                Some(d) => format!("looked in {}", d.display()),
                None => "no shared scenes directory; set EMC_SHARED_DIR".to_string(),
            },
        }),
    }
}

/// The shared scenes directory: the environment variable `EMC_SHARED_DIR` when set (it names
/// the scenes folder itself), else `../shared/scenes` next to the workspace root, if it exists.
pub fn shared_scenes_dir() -> Option<PathBuf> {
    if let Some(d) = std::env::var_os("EMC_SHARED_DIR") {
        let d = PathBuf::from(d);
        return d.is_dir().then_some(d);
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent()?;
    let d = root.join("..").join("shared").join("scenes");
    d.is_dir().then_some(d)
}

/// The file of a shared scene (`NAME.obj`, else `NAME.obj.zst`), if the directory and the file
/// exist.
pub fn shared_scene_path(name: &str) -> Option<PathBuf> {
    let dir = shared_scenes_dir()?;
    [format!("{name}.obj"), format!("{name}.obj.zst")]
        .into_iter()
        .map(|f| dir.join(f))
        .find(|p| p.is_file())
}
