//! The tracer's acceleration structure: any validated BVH2 collapsed into a 4-wide BVH (one SSE
//! register per plane) and an 8-wide BVH (one AVX2 register per plane), child boxes SoA, nodes
//! and triangles in depth-first order, with the depth bound that sizes every stack checked here.
#![deny(unsafe_code)]

use emc_core::Aabb;
use glam::{Vec3, Vec3A};

use crate::bvh::atrbvh::FinalNodes;
use crate::bvh::node::Node;
use crate::bvh::Bvh;
use crate::trace::traverse::prefetch;
use crate::trace::TraceError;

/// Children per node of the 4-wide tree: one SSE register per slab plane (SSE is part of the
/// x86-64 baseline; other targets use the bit-identical scalar test). Also the lane count of
/// the triangle packets, which both trees share.
pub const WIDTH: usize = 4;

/// Children per node of the 8-wide tree: one AVX2 register per slab plane, traversed when the
/// CPU has AVX2 (detected at run time), else by the bit-identical scalar test.
pub const WIDTH8: usize = 8;

/// Deepest wide tree the traversal stacks can hold (root at depth 0).
pub const MAX_DEPTH: usize = 96;

/// Entries of a traversal stack. Popping a node of depth `d` leaves at most `(WIDTH − 1)·d`
/// waiting siblings and pushes at most `WIDTH` children: `(WIDTH − 1)·(MAX_DEPTH + 1) + 1`.
pub const STACK_CAPACITY: usize = (WIDTH - 1) * (MAX_DEPTH + 1) + 1;

/// Entries of a traversal stack of the 8-wide tree (same bound with `WIDTH8`); the larger of
/// the two capacities.
pub const STACK_CAPACITY8: usize = (WIDTH8 - 1) * (MAX_DEPTH + 1) + 1;

/// Child code of an unused slot.
pub const EMPTY: u32 = u32::MAX;
/// Child code flag of a leaf; the low 31 bits are the leaf's first triangle packet.
pub const LEAF: u32 = 1 << 31;
/// Largest triangle id (ids must stay below the leaf flag bit).
pub const MAX_TRIANGLES: usize = (1 << 31) - 1;

/// Up to four triangles of one leaf, SoA, for the SIMD triangle test: 176 bytes.
///
/// ```text
///   v[3j + a][lane] : coordinate a (x, y, z) of vertex j (0, 1, 2) of triangle `lane`
///   id[lane]        : triangle id; unused lanes repeat the last real triangle (same answer)
///   count           : real triangles (1..=4)     last: 1 on the last packet of the leaf
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(16))]
pub struct TriPacket {
    /// Vertex coordinates, see the type docs.
    pub v: [[f32; WIDTH]; 9],
    /// Triangle ids.
    pub id: [u32; WIDTH],
    /// Real triangles in this packet.
    pub count: u32,
    /// 1 when this is the leaf's last packet.
    pub last: u32,
    _pad: [u32; 2],
}

const _: () = assert!(core::mem::size_of::<TriPacket>() == 176);

impl TriPacket {
    /// A packet of `count` triangles, all coordinates and ids zero (to be filled in).
    #[inline(always)]
    pub fn blank(count: u32, last: bool) -> TriPacket {
        TriPacket {
            v: [[0.0; WIDTH]; 9],
            id: [0; WIDTH],
            count,
            last: last as u32,
            _pad: [0; 2],
        }
    }

    /// The packet of triangles `tris` (corners as SIMD lanes, `w` ignored) with ids `ids`, of
    /// which the first `count` are real (the rest repeat a real one); `last` on the leaf's
    /// last packet. On x86-64 the corners are transposed in registers, lanes to rows:
    ///
    /// ```text
    ///   a = x0 y0 z0 ·   unpacklo(a, b) = x0 x1 y0 y1   movelh = x0 x1 x2 x3  (row x)
    ///   b = x1 y1 z1 ·   unpacklo(c, d) = x2 x3 y2 y3   movehl = y0 y1 y2 y3  (row y)
    ///   c = x2 y2 z2 ·   unpackhi(a, b) = z0 z1 · ·     movelh = z0 z1 z2 z3  (row z)
    ///   d = x3 y3 z3 ·   unpackhi(c, d) = z2 z3 · ·
    /// ```
    #[inline(always)]
    pub fn from_lanes(
        tris: [&[Vec3A; 3]; WIDTH],
        ids: [u32; WIDTH],
        count: u32,
        last: bool,
    ) -> TriPacket {
        #[cfg(target_arch = "x86_64")]
        #[allow(unsafe_code)]
        let v = {
            use core::arch::x86_64::{
                __m128, _mm_movehl_ps, _mm_movelh_ps, _mm_unpackhi_ps, _mm_unpacklo_ps,
            };
            let mut v = [[0.0f32; WIDTH]; 9];
            for j in 0..3 {
                let [a, b, c, d]: [__m128; 4] = tris.map(|t| t[j].into());
                // SAFETY: SSE is part of the x86-64 baseline; register shuffles only.
                let rows = unsafe {
                    let (ab, cd) = (_mm_unpacklo_ps(a, b), _mm_unpacklo_ps(c, d));
                    let (abz, cdz) = (_mm_unpackhi_ps(a, b), _mm_unpackhi_ps(c, d));
                    [
                        _mm_movelh_ps(ab, cd),
                        _mm_movehl_ps(cd, ab),
                        _mm_movelh_ps(abz, cdz),
                    ]
                };
                for (a, row) in rows.into_iter().enumerate() {
                    v[3 * j + a] = glam::Vec4::from(row).to_array();
                }
            }
            v
        };
        #[cfg(not(target_arch = "x86_64"))]
        let v: [[f32; WIDTH]; 9] =
            core::array::from_fn(|r| core::array::from_fn(|l| tris[l][r / 3][r % 3]));
        TriPacket {
            v,
            id: ids,
            count,
            last: last as u32,
            _pad: [0; 2],
        }
    }

    /// Packets of four consecutive triangles each (ids = positions in `tris`; the last packet
    /// pads with its last triangle), every packet marked as its leaf's last.
    pub fn of_triangles(tris: &[[Vec3; 3]]) -> Vec<TriPacket> {
        tris.chunks(WIDTH)
            .enumerate()
            .map(|(c, chunk)| {
                let mut p = TriPacket::blank(chunk.len() as u32, true);
                for lane in 0..WIDTH {
                    let k = lane.min(chunk.len() - 1);
                    for (j, v) in chunk[k].iter().enumerate() {
                        p.v[3 * j][lane] = v.x;
                        p.v[3 * j + 1][lane] = v.y;
                        p.v[3 * j + 2][lane] = v.z;
                    }
                    p.id[lane] = (c * WIDTH + k) as u32;
                }
                p
            })
            .collect()
    }

    /// The vertices of lane `lane` as the scalar triangle test takes them.
    #[inline(always)]
    pub fn lane(&self, lane: usize) -> [[f32; 3]; 3] {
        let v = &self.v;
        core::array::from_fn(|j| [v[3 * j][lane], v[3 * j + 1][lane], v[3 * j + 2][lane]])
    }
}

/// One `W`-wide node, 64-byte aligned: 128 bytes (two cache lines) for `W = 4`, 256 bytes
/// (four lines) for `W = 8`.
///
/// ```text
///   W = 4: bytes   0..96 : lo[x], hi[x], lo[y], hi[y], lo[z], hi[z]   each [f32; 4]
///          bytes  96..112: child[4]      bytes 112..128: zero
///   W = 8: bytes   0..192: lo[x], hi[x], lo[y], hi[y], lo[z], hi[z]   each [f32; 8]
///          bytes 192..224: child[8]      bytes 224..256: zero
///   lane = child;  child code  inner: node index | leaf: LEAF | first packet | EMPTY
/// ```
/// An unused lane has the empty box (lo = +inf, hi = −inf), which no ray enters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(64))]
pub struct WideNodeN<const W: usize> {
    /// `planes[2a]` = child minima on axis `a`, `planes[2a + 1]` = child maxima.
    pub planes: [[f32; W]; 6],
    /// Child codes, see the type docs.
    pub child: [u32; W],
    /// Fills the node to its size (no padding bytes: a node is copied in 16-byte pieces).
    _pad: [u32; W],
}

/// The triangles a collapse reads, by id: a triangle list, or an indexed mesh.
pub(crate) trait Corners: Sync {
    /// Number of triangles.
    fn count(&self) -> usize;
    /// Triangle `id`'s corners.
    fn corners(&self, id: u32) -> [Vec3A; 3];
    /// Hint the cache to fetch what [`Corners::corners`] of `id` will read (as far as it can
    /// without waiting for a load).
    fn prefetch(&self, id: u32);
}

impl Corners for [[Vec3; 3]] {
    #[inline(always)]
    fn count(&self) -> usize {
        self.len()
    }

    #[inline(always)]
    fn corners(&self, id: u32) -> [Vec3A; 3] {
        self[id as usize].map(Vec3A::from)
    }

    #[inline(always)]
    fn prefetch(&self, id: u32) {
        // Both ends: a triangle's 36 bytes may straddle two lines.
        if let Some(t) = self.get(id as usize) {
            prefetch(&t[0].x, 1);
            prefetch(&t[2].z, 1);
        }
    }
}

/// An indexed mesh whose indices are checked (every one names a vertex).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Indexed<'a> {
    pub vertices: &'a [Vec3],
    pub indices: &'a [[u32; 3]],
}

impl Corners for Indexed<'_> {
    #[inline(always)]
    fn count(&self) -> usize {
        self.indices.len()
    }

    #[inline(always)]
    fn corners(&self, id: u32) -> [Vec3A; 3] {
        self.indices[id as usize].map(|i| Vec3A::from(self.vertices[i as usize]))
    }

    #[inline(always)]
    fn prefetch(&self, id: u32) {
        // The indices only: the corners' addresses need them loaded.
        if let Some(t) = self.indices.get(id as usize) {
            prefetch(t, 12);
        }
    }
}

/// A node of the 4-wide tree.
pub type WideNode = WideNodeN<WIDTH>;
/// A node of the 8-wide tree.
pub type WideNode8 = WideNodeN<WIDTH8>;

const _: () = assert!(core::mem::size_of::<WideNode>() == 128);
const _: () = assert!(core::mem::size_of::<WideNode8>() == 256);

impl<const W: usize> WideNodeN<W> {
    /// A node with every lane unused.
    pub fn empty() -> WideNodeN<W> {
        let mut planes = [[0.0; W]; 6];
        for a in 0..3 {
            planes[2 * a] = [f32::INFINITY; W];
            planes[2 * a + 1] = [f32::NEG_INFINITY; W];
        }
        WideNodeN {
            planes,
            child: [EMPTY; W],
            _pad: [0; W],
        }
    }

    /// Make lane `lane` the child `code` with box `b` grown by `pad` on every side.
    #[inline(always)]
    pub fn set(&mut self, lane: usize, b: &Aabb, code: u32, pad: f32) {
        let (lo, hi) = ((b.min - pad).to_array(), (b.max + pad).to_array());
        for a in 0..3 {
            self.planes[2 * a][lane] = lo[a];
            self.planes[2 * a + 1][lane] = hi[a];
        }
        self.child[lane] = code;
    }

    /// The box of child `lane` (the empty box for an unused lane).
    pub fn child_box(&self, lane: usize) -> Aabb {
        let p = &self.planes;
        Aabb::new(
            Vec3::new(p[0][lane], p[2][lane], p[4][lane]),
            Vec3::new(p[1][lane], p[3][lane], p[5][lane]),
        )
    }
}

/// A wide BVH over a triangle list, ready to trace: a 4-wide and an 8-wide tree over the
/// same leaves (both refer to the same triangle packets).
#[derive(Clone, Debug)]
pub struct WideBvh {
    /// Nodes of the 4-wide tree in depth-first pre-order; node 0 is the root.
    pub nodes: Vec<WideNode>,
    /// Nodes of the 8-wide tree in depth-first pre-order; node 0 is the root.
    pub nodes8: Vec<WideNode8>,
    /// Triangle packets in leaf order (a leaf's packets are contiguous).
    pub packets: Vec<TriPacket>,
    /// Number of triangles.
    pub triangles: usize,
    /// Largest absolute vertex coordinate (sizes the traversal's absolute culling slack).
    pub max_abs: f32,
    /// Depth of the 4-wide tree (root alone: 0); at most [`MAX_DEPTH`].
    pub depth: usize,
    /// Depth of the 8-wide tree; at most [`MAX_DEPTH`].
    pub depth8: usize,
    /// Number of leaves.
    pub leaves: usize,
}

impl WideBvh {
    /// Collapse a BVH2 built over `tris` (triangle `i` = `tris[i]`) into a wide BVH.
    ///
    /// The tree is first checked by [`Bvh::validate`] against the triangles' boxes (every
    /// triangle exactly once, every box contains its subtree), so no hit can be lost; a tree
    /// deeper than [`MAX_DEPTH`] after collapsing is refused with [`TraceError::TooDeep`].
    /// The 8-wide tree is the SAH-optimal cover of the BVH2 by nodes of up to eight children
    /// and leaves of whole subtrees (see `Plan`); the 4-wide tree is the optimal cover with
    /// up to four children over the same leaves.
    pub fn from_bvh2(bvh: &Bvh, tris: &[[Vec3; 3]]) -> Result<WideBvh, TraceError> {
        let scratch = &mut CollapseScratch::default();
        WideBvh::collapse_bvh2(bvh, tris, true, true, false, WideBvh::empty(), scratch)
    }

    /// [`WideBvh::from_bvh2`] building only the tree of `width` (4 or 8; any other value
    /// builds both), as a traced structure needs; the other tree is left empty.
    pub fn from_bvh2_width(
        bvh: &Bvh,
        tris: &[[Vec3; 3]],
        width: usize,
    ) -> Result<WideBvh, TraceError> {
        let scratch = &mut CollapseScratch::default();
        WideBvh::collapse_width(bvh, tris, width, false, WideBvh::empty(), scratch)
    }

    fn collapse_width(
        bvh: &Bvh,
        tris: &[[Vec3; 3]],
        width: usize,
        trusted: bool,
        old: WideBvh,
        scratch: &mut CollapseScratch,
    ) -> Result<WideBvh, TraceError> {
        match width {
            WIDTH => WideBvh::collapse_bvh2(bvh, tris, true, false, trusted, old, scratch),
            WIDTH8 => WideBvh::collapse_bvh2(bvh, tris, false, true, trusted, old, scratch),
            _ => WideBvh::collapse_bvh2(bvh, tris, true, true, trusted, old, scratch),
        }
    }

    /// The boxes of the root's children in use: of the 8-wide tree when it is built, else of
    /// the 4-wide one; none for an empty structure.
    pub(crate) fn root_child_boxes(&self) -> Vec<Aabb> {
        fn of<const W: usize>(n: &WideNodeN<W>) -> Vec<Aabb> {
            (0..W)
                .filter(|&l| n.child[l] != EMPTY)
                .map(|l| n.child_box(l))
                .collect()
        }
        match (self.nodes8.first(), self.nodes.first()) {
            (Some(n), _) => of(n),
            (None, Some(n)) => of(n),
            (None, None) => Vec::new(),
        }
    }

    /// A structure with no tree (traces nothing).
    pub fn empty() -> WideBvh {
        WideBvh {
            nodes: Vec::new(),
            nodes8: Vec::new(),
            packets: Vec::new(),
            triangles: 0,
            max_abs: 0.0,
            depth: 0,
            depth8: 0,
            leaves: 0,
        }
    }

    /// Record what the fast builder made: `width`'s tree over `triangles` triangles.
    pub(crate) fn set_fast(
        &mut self,
        triangles: usize,
        t: crate::trace::wide_lbvh::FastTree,
        width: usize,
    ) {
        self.triangles = triangles;
        self.max_abs = t.max_abs;
        self.leaves = t.leaves;
        if width == WIDTH8 {
            (self.depth, self.depth8) = (0, t.depth);
        } else {
            (self.depth, self.depth8) = (t.depth, 0);
        }
    }

    /// Width of the tree a traversal uses by default: 8 when the 8-wide tree exists, else 4.
    pub fn width(&self) -> usize {
        if self.nodes8.is_empty() {
            WIDTH
        } else {
            WIDTH8
        }
    }

    fn collapse_bvh2(
        bvh: &Bvh,
        tris: &[[Vec3; 3]],
        four: bool,
        eight: bool,
        trusted: bool,
        old: WideBvh,
        scratch: &mut CollapseScratch,
    ) -> Result<WideBvh, TraceError> {
        if tris.is_empty() {
            return Err(TraceError::NoTriangles);
        }
        if tris.len() > MAX_TRIANGLES {
            return Err(TraceError::TooManyTriangles(tris.len()));
        }
        if let Some(i) = tris.iter().position(|t| !t.iter().all(|v| v.is_finite())) {
            return Err(TraceError::NonFinite(i));
        }
        if !trusted {
            let aabbs: Vec<Aabb> = tris
                .iter()
                .map(|t| Aabb::from_triangle(t[0], t[1], t[2]))
                .collect();
            bvh.validate(&aabbs).map_err(TraceError::InvalidBvh)?;
        }
        let max_abs = tris
            .iter()
            .flatten()
            .fold(0.0f32, |m, v| m.max(v.abs().max_element()));
        WideBvh::collapse_checked(bvh, tris, max_abs, four, eight, old, scratch, Prep::Fill)
    }

    /// [`WideBvh::from_bvh2_width`] into this structure, for a BVH2 from this crate's own
    /// builders over an indexed mesh whose indices and vertices are checked (largest absolute
    /// coordinate `max_abs`): the corners are read through the indices (no triangle list), and
    /// the node and packet buffers of the structure and the plans of `scratch` are reused (a
    /// rebuild faults no fresh pages for them and frees nothing). The BVH2's validation runs
    /// in debug builds only (the tests validate the wide trees), because those builders place
    /// every triangle once and bound it by construction. On an error the structure is left
    /// empty. `prep` says how the plan is made (see [`Prep`]).
    pub(crate) fn rebuild_from_own_mesh(
        &mut self,
        bvh: &Bvh,
        prep: Prep,
        mesh: Indexed<'_>,
        max_abs: f32,
        width: usize,
        scratch: &mut CollapseScratch,
    ) -> Result<(), TraceError> {
        let n = mesh.count();
        if n > MAX_TRIANGLES {
            return Err(TraceError::TooManyTriangles(n));
        }
        if cfg!(debug_assertions) {
            let aabbs: Vec<Aabb> = (0..n as u32)
                .map(|i| {
                    let [a, b, c] = mesh.corners(i).map(Vec3::from);
                    Aabb::from_triangle(a, b, c)
                })
                .collect();
            bvh.validate(&aabbs).map_err(TraceError::InvalidBvh)?;
        }
        let old = std::mem::replace(self, WideBvh::empty());
        let (four, eight) = (width != WIDTH8, width != WIDTH);
        *self = WideBvh::collapse_checked(bvh, &mesh, max_abs, four, eight, old, scratch, prep)?;
        Ok(())
    }

    /// The collapse of a BVH2 checked against `tris` (at least one triangle, every corner
    /// finite, largest absolute coordinate `max_abs`), its plan made as `prep` says.
    #[allow(clippy::too_many_arguments)]
    fn collapse_checked<T: Corners + ?Sized>(
        bvh: &Bvh,
        tris: &T,
        max_abs: f32,
        four: bool,
        eight: bool,
        old: WideBvh,
        scratch: &mut CollapseScratch,
        prep: Prep,
    ) -> Result<WideBvh, TraceError> {
        // Child boxes are padded by 2^-16 of the largest coordinate: the triangle test rounds
        // `vertex − origin` to ulps of the coordinates, so with needles thinner than an ulp it
        // can report a hit a hair outside the exact box; the pad (2^7 ulps) keeps such hits
        // inside. It covers origins no farther from 0 than the geometry (then |o| ≤ M).
        let pad = max_abs * (1.0 / 65536.0);
        // The buffers of `old` (empty for a first build), cleared.
        let (old4, old8, mut packets) = (old.nodes, old.nodes8, old.packets);
        crate::buffers::cleared_with_room(&mut packets, tris.count() / 2);
        let mut leaves = 0;
        let CollapseScratch {
            plan4,
            plan8,
            walk,
            emit: prims,
            leaf_codes,
        } = scratch;
        // The plan of the tree that chooses the leaves: the 8-wide one when it is built, else
        // the 4-wide one alone (planned in place, it is there already).
        let may_leaf = |_, p| may_leaf_of(p);
        match (prep, eight) {
            (Prep::Fill, true) => plan8.fill(bvh, may_leaf, |_| false, true, walk),
            (Prep::Fill, false) => plan4.fill(bvh, may_leaf, |_| false, true, walk),
            (Prep::Planned, _) => {}
        }
        if !eight {
            let (nodes, depth) = collapse::<WIDTH>(
                bvh,
                plan4,
                pad,
                |n| {
                    leaves += 1;
                    emit_leaf(&mut packets, prims, bvh, n, tris)
                },
                old4,
                walk,
            )?;
            return Ok(WideBvh {
                nodes,
                nodes8: Vec::new(),
                packets,
                triangles: tris.count(),
                max_abs,
                depth,
                depth8: 0,
                leaves,
            });
        }
        // The 8-wide tree chose the leaves (and emits their packets in its depth-first order);
        // the 4-wide tree is planned over exactly those leaves and shares them.
        if four {
            leaf_codes.clear();
            leaf_codes.resize(bvh.nodes.len(), EMPTY);
        }
        let (nodes8, depth8) = collapse::<WIDTH8>(
            bvh,
            plan8,
            pad,
            |n| {
                let code = emit_leaf(&mut packets, prims, bvh, n, tris);
                if four {
                    leaf_codes[n as usize] = code;
                }
                leaves += 1;
                code
            },
            old8,
            walk,
        )?;
        let (nodes, depth) = if four {
            plan4.fill(
                bvh,
                |_, _| false,
                |n| leaf_codes[n as usize] != EMPTY,
                false,
                walk,
            );
            collapse::<WIDTH>(bvh, plan4, pad, |n| leaf_codes[n as usize], old4, walk)?
        } else {
            (Vec::new(), 0)
        };
        Ok(WideBvh {
            nodes,
            nodes8,
            packets,
            triangles: tris.count(),
            max_abs,
            depth,
            depth8,
            leaves,
        })
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// SAH cost of the traced tree, relative to its root box: `Σ A(node) + Σ A(leaf) · packets`
    /// over wide nodes and leaves (`A`: half area of the box a parent holds for it, the root's
    /// being the union of its children), the model the collapse optimises (a node test and a
    /// packet test cost 1 per unit of area).
    pub fn sah(&self) -> f64 {
        fn walk<const W: usize>(w: &WideBvh, nodes: &[WideNodeN<W>]) -> f64 {
            if nodes.is_empty() {
                return 0.0;
            }
            let root = &nodes[0];
            let rb = (0..W).fold(Aabb::EMPTY, |b, l| {
                if root.child[l] == EMPTY {
                    b
                } else {
                    b.union(&root.child_box(l))
                }
            });
            let ra = half_area(&rb) as f64;
            let mut total = ra;
            let mut stack = vec![0u32];
            while let Some(i) = stack.pop() {
                let n = &nodes[i as usize];
                for l in 0..W {
                    let c = n.child[l];
                    if c == EMPTY {
                        continue;
                    }
                    let a = half_area(&n.child_box(l)) as f64;
                    if c & LEAF != 0 {
                        let mut pi = (c & !LEAF) as usize;
                        let mut k = 1;
                        while w.packets[pi].last == 0 {
                            pi += 1;
                            k += 1;
                        }
                        total += a * k as f64;
                    } else {
                        total += a;
                        stack.push(c);
                    }
                }
            }
            if ra > 0.0 {
                total / ra
            } else {
                0.0
            }
        }
        if self.nodes8.is_empty() {
            walk(self, &self.nodes)
        } else {
            walk(self, &self.nodes8)
        }
    }

    /// Check the traced tree against the triangles it was built over (`tri(id)`: the corners
    /// of triangle `id`, `count` of them): every triangle in exactly one leaf lane with its
    /// exact corners, packets well formed, every child box containing its subtree's
    /// triangles, no node reached twice or left unreached, depth and leaf count as recorded.
    /// The tests and debug builds run it on every build; a release build trusts the builder.
    pub fn validate(&self, count: usize, tri: impl Fn(u32) -> [Vec3; 3]) -> Result<(), String> {
        fn walk<const W: usize>(
            w: &WideBvh,
            nodes: &[WideNodeN<W>],
            count: usize,
            tri: &dyn Fn(u32) -> [Vec3; 3],
            recorded_depth: usize,
        ) -> Result<(), String> {
            if nodes.is_empty() {
                return Err("no root node".into());
            }
            // (node, depth); boxes are checked per lane against the subtree's exact bounds,
            // computed by a second, post-order walk.
            fn subtree<const W: usize>(
                w: &WideBvh,
                nodes: &[WideNodeN<W>],
                code: u32,
                d: usize,
                st: &mut (Vec<bool>, Vec<bool>, usize, usize),
                count: usize,
                tri: &dyn Fn(u32) -> [Vec3; 3],
            ) -> Result<Aabb, String> {
                if code & LEAF != 0 {
                    st.2 += 1;
                    let mut pi = (code & !LEAF) as usize;
                    let mut b = Aabb::EMPTY;
                    loop {
                        let p = w
                            .packets
                            .get(pi)
                            .ok_or(format!("leaf {code:#x}: packet {pi} missing"))?;
                        if p.count == 0 || p.count as usize > WIDTH {
                            return Err(format!("packet {pi}: {} triangles", p.count));
                        }
                        for lane in 0..WIDTH {
                            let real = lane.min(p.count as usize - 1);
                            let id = p.id[lane];
                            if id != p.id[real] {
                                return Err(format!(
                                    "packet {pi}: spare lane {lane} is not a copy"
                                ));
                            }
                            if lane >= p.count as usize {
                                continue;
                            }
                            if id as usize >= count {
                                return Err(format!("packet {pi}: triangle {id} of {count}"));
                            }
                            if std::mem::replace(&mut st.1[id as usize], true) {
                                return Err(format!("triangle {id} is in two leaves"));
                            }
                            let t = tri(id);
                            let got = p.lane(lane);
                            for (j, v) in t.iter().enumerate() {
                                if v.to_array().map(f32::to_bits) != got[j].map(f32::to_bits) {
                                    return Err(format!(
                                        "packet {pi}: triangle {id} corner {j} differs"
                                    ));
                                }
                                b.grow(*v);
                            }
                        }
                        if p.last != 0 {
                            break;
                        }
                        pi += 1;
                    }
                    return Ok(b);
                }
                let i = code as usize;
                if i >= nodes.len() {
                    return Err(format!("child {i} outside the {} nodes", nodes.len()));
                }
                if std::mem::replace(&mut st.0[i], true) {
                    return Err(format!("node {i} is reached twice"));
                }
                st.3 = st.3.max(d);
                if d > MAX_DEPTH {
                    return Err(format!("depth {d} exceeds {MAX_DEPTH}"));
                }
                let n = &nodes[i];
                let mut total = Aabb::EMPTY;
                let mut used = 0;
                for lane in 0..W {
                    let c = n.child[lane];
                    let lb = n.child_box(lane);
                    if c == EMPTY {
                        if lb.min.cmple(lb.max).any() {
                            return Err(format!("node {i}: unused lane {lane} has a box"));
                        }
                        continue;
                    }
                    used += 1;
                    let sb = subtree(w, nodes, c, d + 1, st, count, tri)?;
                    if !lb.contains(&sb) {
                        return Err(format!("node {i} lane {lane}: box {lb:?} misses {sb:?}"));
                    }
                    total = total.union(&sb);
                }
                if used == 0 {
                    return Err(format!("node {i} has no child"));
                }
                Ok(total)
            }
            let mut st = (vec![false; nodes.len()], vec![false; count], 0usize, 0usize);
            subtree(w, nodes, 0, 0, &mut st, count, tri)?;
            let (seen_node, seen_tri, leaves, depth) = st;
            // Nodes nobody refers to are allowed only when empty (reserved, unused).
            if let Some(i) = seen_node
                .iter()
                .position(|&s| !s)
                .filter(|&i| nodes[i].child.iter().any(|&c| c != EMPTY))
            {
                return Err(format!("node {i} is not reachable from the root"));
            }
            if let Some(t) = seen_tri.iter().position(|&s| !s) {
                return Err(format!("triangle {t} is in no leaf"));
            }
            if leaves != w.leaves {
                return Err(format!("{leaves} leaves, {} recorded", w.leaves));
            }
            if depth != recorded_depth {
                return Err(format!("depth {depth}, {recorded_depth} recorded"));
            }
            Ok(())
        }
        if count != self.triangles {
            return Err(format!("{count} triangles given, {} built", self.triangles));
        }
        if !self.nodes8.is_empty() {
            walk(self, &self.nodes8, count, &tri, self.depth8)?;
        }
        if !self.nodes.is_empty() {
            walk(self, &self.nodes, count, &tri, self.depth)?;
        }
        if self.nodes.is_empty() && self.nodes8.is_empty() {
            return Err("no tree".into());
        }
        Ok(())
    }

    /// Bytes of nodes and triangle data.
    pub fn memory_bytes(&self) -> usize {
        self.nodes.len() * core::mem::size_of::<WideNode>()
            + self.nodes8.len() * core::mem::size_of::<WideNode8>()
            + self.packets.len() * core::mem::size_of::<TriPacket>()
    }
}

/// Cost of testing one wide node, per unit of its surface area (the SAH's `Ct`).
const COST_NODE: f32 = 1.0;
/// Cost of testing one triangle packet, per unit of its leaf's surface area (`Ci` per packet:
/// one to four triangles cost the same SIMD pass).
const COST_PACKET: f32 = 1.0;
/// Most triangles the collapse gathers from several BVH2 leaves into one wide leaf (a BVH2
/// leaf that is larger on its own stays whole).
const MAX_LEAF_TRIANGLES: u32 = 8;

/// The SAH-optimal covers of every BVH2 subtree by at most `i` wide-tree children
/// (`i = 1..=W`), computed bottom-up in the manner of Ylitie, Karras and Laine (2017).
///
/// ```text
///   cost(n, 1) = min(leaf(n), Cn·A(n) + dist(n, W))      n as one child: a leaf or a node
///   cost(n, i) = min(cost(n, i − 1), dist(n, i))          i ≥ 2
///   dist(n, j) = min over k in 1..j of cost(l, k) + cost(r, j − k)   (l, r: n's children)
///   leaf(n)    = Cp·A(n)·⌈P(n)/4⌉   when n may be a leaf, else +inf
/// ```
/// A BVH2 leaf is always one leaf (`cost(n, i) = leaf(n)`). `A` is the half surface area.
/// One row per BVH2 node: everything the planning and the collapse read of a node in one
/// place (48 bytes at width 8, one or two cache lines, where four arrays took four).
#[derive(Clone, Debug, Default)]
struct Plan<const W: usize> {
    rows: Vec<Row<W>>,
}

/// The plan of one BVH2 node `n`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Row<const W: usize> {
    /// `cost[i − 1]` = `cost(n, i)`.
    cost: [f32; W],
    /// `split[j − 1]` = the `k` of `dist(n, j)` (slots given to the left child), j ≥ 2.
    split: [u8; W],
    /// Triangles under `n`.
    prims: u32,
    /// `n`, taken as one child, is a leaf.
    leaf: bool,
}

impl<const W: usize> Default for Row<W> {
    fn default() -> Row<W> {
        Row {
            cost: [0.0; W],
            split: [0; W],
            prims: 0,
            leaf: false,
        }
    }
}

impl<const W: usize> Row<W> {
    /// The row of a leaf of `p` triangles and half area `a`.
    #[inline(always)]
    fn leaf(a: f32, p: u32) -> Row<W> {
        Row {
            cost: [leaf_cost(a, p); W],
            split: [0; W],
            prims: p,
            leaf: true,
        }
    }

    /// The row of an inner node of half area `a` from its children's rows `l` and `r`;
    /// `may_leaf(triangles)` says whether it may become one leaf.
    #[inline(always)]
    fn inner(l: &Row<W>, r: &Row<W>, a: f32, may_leaf: impl Fn(u32) -> bool) -> Row<W> {
        let p = l.prims + r.prims;
        let (dist, split) = crate::trace::cover::dist(&l.cost, &r.cost);
        let inner = COST_NODE * a + dist[W - 1];
        let as_leaf = if may_leaf(p) {
            leaf_cost(a, p)
        } else {
            f32::INFINITY
        };
        let mut cost = [0.0f32; W];
        let leaf = as_leaf <= inner;
        cost[0] = if leaf { as_leaf } else { inner };
        for j in 2..=W {
            cost[j - 1] = cost[j - 2].min(dist[j - 1]);
        }
        Row {
            cost,
            split,
            prims: p,
            leaf,
        }
    }
}

/// The work lists of the collapse (kept between builds).
#[derive(Clone, Debug, Default)]
struct Walk {
    /// The nodes in pre-order.
    pre: Vec<u32>,
    stack: Vec<u32>,
    /// `Plan::children`'s work list and result.
    todo: Vec<(u32, usize)>,
    kids: Vec<u32>,
    inner: Vec<(u32, usize)>,
    /// The emission's work list (BVH2 node, wide parent, lane, depth).
    work: Vec<(u32, usize, usize, usize)>,
}

/// The buffers of the wide collapse, kept for the next one: both plans, the work lists, the
/// leaf emission's lists and the 8-wide leaves' codes (for a 4-wide tree over them).
#[derive(Clone, Debug, Default)]
pub struct CollapseScratch {
    plan4: Plan<WIDTH>,
    plan8: Plan<WIDTH8>,
    walk: Walk,
    emit: (Vec<u32>, Vec<u32>),
    leaf_codes: Vec<u32>,
}

impl<const W: usize> Plan<W> {
    /// Plan the collapse of the validated `bvh` (every entry of the plan rewritten for the
    /// nodes the collapse can reach). `may_leaf(n, triangles)` says whether inner BVH2 node
    /// `n`, whose subtree holds `triangles`, may become one leaf; `forced(n)` makes node `n` a
    /// leaf whatever it costs (its subtree is then never opened). With `index_order`, a tree
    /// whose children all sit after their parents (depth-first layouts) is planned in reverse
    /// index order, one pass front to back over its arrays, and every node is planned (also
    /// those below forced nodes: the answers are the same, the work larger).
    fn fill(
        &mut self,
        bvh: &Bvh,
        may_leaf: impl Fn(u32, u32) -> bool,
        forced: impl Fn(u32) -> bool,
        index_order: bool,
        walk: &mut Walk,
    ) {
        let n = bvh.nodes.len();
        let plan = self;
        plan.size_for(n);
        let mut step = |i: u32| {
            let node = &bvh.nodes[i as usize];
            let a = half_area(&node.bounds);
            let at = i as usize;
            if node.is_leaf() || forced(i) {
                let p = if node.is_leaf() {
                    node.count()
                } else {
                    subtree_triangles(bvh, i)
                };
                plan.rows[at] = Row::leaf(a, p);
            } else {
                let (l, r) = (node.left() as usize, node.right() as usize);
                plan.rows[at] = Row::inner(&plan.rows[l], &plan.rows[r], a, |p| may_leaf(i, p));
            }
        };
        if index_order && children_after_parents(bvh) {
            (0..n as u32).rev().for_each(step);
            return;
        }
        // Pre-order; its reverse visits children before parents.
        let pre = &mut walk.pre;
        pre.clear();
        let stack = &mut walk.stack;
        stack.clear();
        stack.push(bvh.root);
        while let Some(i) = stack.pop() {
            pre.push(i);
            let node = &bvh.nodes[i as usize];
            if !node.is_leaf() && !forced(i) {
                stack.push(node.right());
                stack.push(node.left());
            }
        }
        pre.iter().rev().for_each(|&i| step(i));
    }

    /// Size the plan for a BVH2 of `n` nodes (every entry the planning reaches is rewritten).
    fn size_for(&mut self, n: usize) {
        crate::buffers::resized(&mut self.rows, n, Row::default());
    }

    /// The BVH2 nodes that become the children of the wide node made of inner node `n`, in
    /// depth-first order (`todo`: a work list).
    fn children(&self, bvh: &Bvh, n: u32, out: &mut Vec<u32>, todo: &mut Vec<(u32, usize)>) {
        out.clear();
        let node = &bvh.nodes[n as usize];
        let k = self.rows[n as usize].split[W - 1] as usize;
        // (BVH2 node, slots it may use), right part pushed first so the left comes out first.
        todo.clear();
        todo.extend([(node.right(), W - k), (node.left(), k)]);
        while let Some((m, mut i)) = todo.pop() {
            let c = &self.rows[m as usize].cost;
            // Fewer slots give the same cost: use fewer (ties go to the smaller cover).
            while i > 1 && c[i - 1] == c[i - 2] {
                i -= 1;
            }
            if i == 1 {
                out.push(m);
            } else {
                let mn = &bvh.nodes[m as usize];
                let k = self.rows[m as usize].split[i - 1] as usize;
                todo.push((mn.right(), i - k));
                todo.push((mn.left(), k));
            }
        }
    }
}

/// Whether every inner node's children have higher indices than it (so a pass in reverse
/// index order meets children before parents) and the root is node 0: true of depth-first
/// layouts. One pass front to back.
fn children_after_parents(bvh: &Bvh) -> bool {
    bvh.root == 0
        && bvh.nodes.iter().enumerate().all(|(i, node)| {
            node.is_leaf() || (node.left() as usize > i && node.right() as usize > i)
        })
}

/// Half the surface area of `b`.
fn half_area(b: &Aabb) -> f32 {
    let e = b.max - b.min;
    e.x * e.y + e.y * e.z + e.z * e.x
}

/// Cost of a leaf of `p` triangles and half area `a`: one packet test per 4 triangles.
fn leaf_cost(a: f32, p: u32) -> f32 {
    COST_PACKET * a * p.div_ceil(WIDTH as u32) as f32
}

/// Whether an inner BVH2 node over `p` triangles may become one leaf of the wide trees.
#[inline(always)]
fn may_leaf_of(p: u32) -> bool {
    p <= MAX_LEAF_TRIANGLES
}

/// How [`WideBvh::rebuild_from_own_mesh`] gets its plan.
#[derive(Debug)]
pub(crate) enum Prep {
    /// Planned over the BVH2 as it is.
    Fill,
    /// Planned already, node by node, by [`CollapseScratch::plan_in_place`] of the traced
    /// width over this BVH2.
    Planned,
}

/// The plan of one width filled in place, node by node, as a restructuring's last pass
/// finishes the nodes ([`FinalNodes`]): the rows of `Plan::fill`, written through pointers into
/// the plan's arrays (sized for the tree before), so that threads can fill the rows of the
/// subtrees they own at once. Each row is computed while its node and its children's rows are
/// in the cache, and the collapse then needs no walk of its own before emitting (a walk of a
/// restructured tree reads nodes scattered over its arrays).
#[derive(Debug)]
pub(crate) struct PlanInPlace<'a, const W: usize> {
    rows: *mut Row<W>,
    len: usize,
    _plan: core::marker::PhantomData<&'a mut Plan<W>>,
}

// SAFETY: the rows are written only through `FinalNodes::node`, whose contract gives each
// node's row to one thread at a time and orders a node's children's rows before it.
#[allow(unsafe_code)]
unsafe impl<const W: usize> Sync for PlanInPlace<'_, W> {}

impl<'a, const W: usize> PlanInPlace<'a, W> {
    /// `plan` sized for a BVH2 of `n` nodes, to be filled.
    fn new(plan: &'a mut Plan<W>, n: usize) -> PlanInPlace<'a, W> {
        plan.size_for(n);
        PlanInPlace {
            rows: plan.rows.as_mut_ptr(),
            len: n,
            _plan: core::marker::PhantomData,
        }
    }
}

impl<const W: usize> FinalNodes for PlanInPlace<'_, W> {
    #[inline(always)]
    #[allow(unsafe_code)]
    unsafe fn node(&self, i: u32, node: &Node) {
        let at = i as usize;
        assert!(at < self.len, "node index out of range");
        let a = half_area(&node.bounds);
        // SAFETY: every index is checked against the rows' length `len`; row `at` belongs to
        // this thread and the children's rows were written before it, published to this
        // thread (the `FinalNodes` contract); no reference into the rows outlives the call.
        unsafe {
            let row = if node.is_leaf() {
                Row::leaf(a, node.count())
            } else {
                let (l, r) = (node.left() as usize, node.right() as usize);
                assert!(l < self.len && r < self.len, "child index out of range");
                Row::inner(&*self.rows.add(l), &*self.rows.add(r), a, may_leaf_of)
            };
            *self.rows.add(at) = row;
        }
    }
}

/// The in-place plan of the traced width (see [`CollapseScratch::plan_in_place`]).
#[derive(Debug)]
pub(crate) enum InPlace<'a> {
    /// Of the 4-wide tree.
    Four(PlanInPlace<'a, WIDTH>),
    /// Of the 8-wide tree.
    Eight(PlanInPlace<'a, WIDTH8>),
}

impl FinalNodes for InPlace<'_> {
    #[inline(always)]
    #[allow(unsafe_code)]
    unsafe fn node(&self, i: u32, node: &Node) {
        // SAFETY: the caller keeps the contract, passed on as it is.
        unsafe {
            match self {
                InPlace::Four(p) => p.node(i, node),
                InPlace::Eight(p) => p.node(i, node),
            }
        }
    }
}

impl CollapseScratch {
    /// Whether the plan of `width` holds, for every node of `bvh`, the row `Plan::fill`
    /// computes (the check of a plan made in place).
    #[cfg(test)]
    pub(crate) fn plan_is_fill_of(&self, bvh: &Bvh, width: usize) -> bool {
        fn same<const W: usize>(plan: &Plan<W>, bvh: &Bvh) -> bool {
            let mut fresh = Plan::<W>::default();
            fresh.fill(
                bvh,
                |_, p| may_leaf_of(p),
                |_| false,
                true,
                &mut Walk::default(),
            );
            plan.rows.len() == bvh.nodes.len() && fresh.rows == plan.rows
        }
        if width == WIDTH {
            same(&self.plan4, bvh)
        } else {
            same(&self.plan8, bvh)
        }
    }

    /// The plan of the tree of `width` (4 or 8; the 8-wide one otherwise) sized for a BVH2
    /// of `n` nodes, to be filled node by node by a restructuring's last pass; the collapse
    /// of that BVH2 at that width then takes [`Prep::Planned`].
    pub(crate) fn plan_in_place(&mut self, n: usize, width: usize) -> InPlace<'_> {
        if width == WIDTH {
            InPlace::Four(PlanInPlace::new(&mut self.plan4, n))
        } else {
            InPlace::Eight(PlanInPlace::new(&mut self.plan8, n))
        }
    }
}

/// Triangles under BVH2 node `n`.
fn subtree_triangles(bvh: &Bvh, n: u32) -> u32 {
    let mut total = 0;
    let mut stack = vec![n];
    while let Some(i) = stack.pop() {
        let node = &bvh.nodes[i as usize];
        if node.is_leaf() {
            total += node.count();
        } else {
            stack.push(node.right());
            stack.push(node.left());
        }
    }
    total
}

/// Emit the `W`-wide tree `plan` describes for the validated, non-empty `bvh`. `leaf(n)` gives
/// the child code of leaf `n` (called once per leaf, in depth-first order). Returns the nodes
/// (depth-first pre-order) and the depth.
fn collapse<const W: usize>(
    bvh: &Bvh,
    plan: &Plan<W>,
    pad: f32,
    mut leaf: impl FnMut(u32) -> u32,
    mut nodes: Vec<WideNodeN<W>>,
    walk: &mut Walk,
) -> Result<(Vec<WideNodeN<W>>, usize), TraceError> {
    crate::buffers::cleared_with_room(&mut nodes, bvh.nodes.len() / W + 1);
    let mut max_depth = 0;
    let root = &bvh.nodes[bvh.root as usize];
    nodes.push(WideNodeN::empty());
    if plan.rows[bvh.root as usize].leaf {
        let code = leaf(bvh.root);
        nodes[0].set(0, &root.bounds, code, pad);
        return Ok((nodes, 0));
    }
    let Walk {
        todo,
        kids,
        inner,
        work,
        ..
    } = walk;
    // Work items: (BVH2 node, wide parent index, lane, depth of the new wide node).
    work.clear();
    work.push((bvh.root, usize::MAX, 0, 0));
    while let Some((n2, parent, lane, depth)) = work.pop() {
        if depth > MAX_DEPTH {
            return Err(TraceError::TooDeep {
                depth,
                max: MAX_DEPTH,
            });
        }
        max_depth = max_depth.max(depth);
        let me = if parent == usize::MAX {
            0
        } else {
            let i = nodes.len();
            nodes.push(WideNodeN::empty());
            nodes[parent].child[lane] = i as u32;
            i
        };
        plan.children(bvh, n2, kids, todo);
        // Leaves first (their triangles follow the parent), then inner children in order.
        inner.clear();
        for (lane, &k) in kids.iter().enumerate() {
            let kn = &bvh.nodes[k as usize];
            if plan.rows[k as usize].leaf {
                let code = leaf(k);
                nodes[me].set(lane, &kn.bounds, code, pad);
            } else {
                nodes[me].set(lane, &kn.bounds, EMPTY, pad);
                inner.push((k, lane));
            }
        }
        for &(k, lane) in inner.iter().rev() {
            work.push((k, me, lane, depth + 1));
        }
    }
    Ok((nodes, max_depth))
}

/// How many primitives ahead of a leaf's own (in the BVH2's primitive order, which the
/// depth-first emission follows for the builders' trees) triangles are prefetched: a
/// one-thread quality build of pbrt-bathroom 4% faster, stanford-dragon within noise
/// (alternating builds in one process).
const LEAF_AHEAD: usize = 16;

/// Append the triangle packets of BVH2 node `n`'s subtree (one leaf of the wide trees) and
/// return its child code.
fn emit_leaf<T: Corners + ?Sized>(
    packets: &mut Vec<TriPacket>,
    (prims, stack): &mut (Vec<u32>, Vec<u32>),
    bvh: &Bvh,
    n: u32,
    tris: &T,
) -> u32 {
    prims.clear();
    stack.clear();
    stack.push(n);
    while let Some(i) = stack.pop() {
        let node = &bvh.nodes[i as usize];
        if node.is_leaf() {
            let f = node.first() as usize;
            let range = f..f + node.count() as usize;
            // What the triangles a little further on will read.
            let ahead = (range.start + LEAF_AHEAD).min(bvh.prim_indices.len())
                ..(range.end + LEAF_AHEAD).min(bvh.prim_indices.len());
            for &id in &bvh.prim_indices[ahead] {
                tris.prefetch(id);
            }
            prims.extend_from_slice(&bvh.prim_indices[range]);
        } else {
            stack.push(node.right());
            stack.push(node.left());
        }
    }
    let first = packets.len() as u32;
    let chunks = prims.chunks(WIDTH);
    let k = chunks.len();
    for (c, chunk) in chunks.enumerate() {
        let lane = |l: usize| chunk[l.min(chunk.len() - 1)];
        let corners: [[Vec3A; 3]; WIDTH] = core::array::from_fn(|l| tris.corners(lane(l)));
        packets.push(TriPacket::from_lanes(
            core::array::from_fn(|l| &corners[l]),
            core::array::from_fn(lane),
            chunk.len() as u32,
            c + 1 == k,
        ));
    }
    LEAF | first
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::node::Node;

    /// A median-split BVH2 over `tris` with one triangle per leaf (node 0 is the root).
    fn median(tris: &[[Vec3; 3]]) -> Bvh {
        fn build(tris: &[[Vec3; 3]], lo: usize, hi: usize, nodes: &mut Vec<Node>) -> u32 {
            let b = tris[lo..hi].iter().fold(Aabb::EMPTY, |b, t| {
                b.union(&Aabb::from_triangle(t[0], t[1], t[2]))
            });
            let me = nodes.len() as u32;
            if hi - lo == 1 {
                nodes.push(Node::leaf(b, lo as u32, 1));
                return me;
            }
            nodes.push(Node::leaf(b, 0, 1));
            let mid = (lo + hi) / 2;
            let l = build(tris, lo, mid, nodes);
            let r = build(tris, mid, hi, nodes);
            nodes[me as usize] = Node::inner(b, l, r);
            me
        }
        let mut nodes = Vec::new();
        build(tris, 0, tris.len(), &mut nodes);
        Bvh {
            nodes,
            prim_indices: (0..tris.len() as u32).collect(),
            root: 0,
        }
    }

    /// Leaf codes of a wide tree, in node order.
    fn leaf_codes<const W: usize>(nodes: &[WideNodeN<W>]) -> Vec<u32> {
        let mut v: Vec<u32> = nodes
            .iter()
            .flat_map(|n| n.child)
            .filter(|&c| c != EMPTY && c & LEAF != 0)
            .collect();
        v.sort_unstable();
        v
    }

    #[test]
    fn collapse_covers_every_triangle_once_with_shared_bounded_leaves() {
        // Triangles of very different sizes along a line, so the SAH has choices to make.
        let tris: Vec<[Vec3; 3]> = (0..1000)
            .map(|i| {
                let x = (i as f32).powf(1.3);
                let s = 0.1 + (i % 7) as f32;
                [
                    Vec3::new(x, 0.0, 0.0),
                    Vec3::new(x + s, 0.0, (i % 3) as f32),
                    Vec3::new(x, s, 0.0),
                ]
            })
            .collect();
        let w = WideBvh::from_bvh2(&median(&tris), &tris).unwrap();
        // Every triangle in exactly one real packet lane.
        let mut seen = vec![0u32; tris.len()];
        for p in &w.packets {
            for &id in &p.id[..p.count as usize] {
                seen[id as usize] += 1;
            }
        }
        assert!(seen.iter().all(|&c| c == 1));
        // Both trees reach the same leaves, each leaf once; merged leaves stay within the bound.
        let l8 = leaf_codes(&w.nodes8);
        assert_eq!(l8, leaf_codes(&w.nodes));
        assert_eq!(l8.len(), w.leaves);
        assert!(l8.windows(2).all(|p| p[0] < p[1]));
        for &c in &l8 {
            let (mut i, mut total) = ((c & !LEAF) as usize, 0);
            loop {
                total += w.packets[i].count;
                if w.packets[i].last != 0 {
                    break;
                }
                i += 1;
            }
            assert!((1..=MAX_LEAF_TRIANGLES).contains(&total));
        }
        // The cover uses the width: far fewer nodes than a binary tree.
        assert!(w.nodes8.len() * 4 < tris.len() && w.leaves < tris.len());
    }
}
