//! The tracer's acceleration structure: any validated BVH2 collapsed into a 4-wide BVH (one SSE
//! register per plane) and an 8-wide BVH (one AVX2 register per plane), child boxes SoA, nodes
//! and triangles in depth-first order, with the depth bound that sizes every stack checked here.
#![forbid(unsafe_code)]

use emc_core::Aabb;
use glam::Vec3;

use crate::bvh::Bvh;
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
///          bytes  96..112: child[4]      bytes 112..128: padding
///   W = 8: bytes   0..192: lo[x], hi[x], lo[y], hi[y], lo[z], hi[z]   each [f32; 8]
///          bytes 192..224: child[8]      bytes 224..256: padding
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
        }
    }

    fn set(&mut self, lane: usize, b: &Aabb, code: u32, pad: f32) {
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
    /// Each wide node takes its BVH2 node's two children and repeatedly opens the inner child
    /// of largest surface area until it has four (eight) children or only leaves.
    pub fn from_bvh2(bvh: &Bvh, tris: &[[Vec3; 3]]) -> Result<WideBvh, TraceError> {
        if tris.is_empty() {
            return Err(TraceError::NoTriangles);
        }
        if tris.len() > MAX_TRIANGLES {
            return Err(TraceError::TooManyTriangles(tris.len()));
        }
        let aabbs: Vec<Aabb> = tris
            .iter()
            .map(|t| Aabb::from_triangle(t[0], t[1], t[2]))
            .collect();
        if let Some(i) = aabbs.iter().position(|b| !b.is_finite()) {
            return Err(TraceError::NonFinite(i));
        }
        bvh.validate(&aabbs).map_err(TraceError::InvalidBvh)?;
        let max_abs = aabbs.iter().fold(0.0f32, |m, b| {
            m.max(b.min.abs().max_element())
                .max(b.max.abs().max_element())
        });
        // Child boxes are padded by 2^-16 of the largest coordinate: the triangle test rounds
        // `vertex − origin` to ulps of the coordinates, so with needles thinner than an ulp it
        // can report a hit a hair outside the exact box; the pad (2^7 ulps) keeps such hits
        // inside. It covers origins no farther from 0 than the geometry (then |o| ≤ M).
        let pad = max_abs * (1.0 / 65536.0);
        let mut packets = Vec::with_capacity(tris.len() / 2);
        // Leaf code of every BVH2 leaf, written by the 4-wide collapse (which emits the
        // packets in its depth-first order) and read by the 8-wide one: both open only inner
        // nodes, so they reach the same BVH2 leaves.
        let mut leaf_codes = vec![EMPTY; bvh.nodes.len()];
        let mut leaves = 0;
        let (nodes, depth) = collapse::<WIDTH>(bvh, pad, |n| {
            let code = emit_leaf(&mut packets, bvh, n, tris);
            leaf_codes[n as usize] = code;
            leaves += 1;
            code
        })?;
        let (nodes8, depth8) = collapse::<WIDTH8>(bvh, pad, |n| leaf_codes[n as usize])?;
        Ok(WideBvh {
            nodes,
            nodes8,
            packets,
            triangles: tris.len(),
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

    /// Bytes of nodes and triangle data.
    pub fn memory_bytes(&self) -> usize {
        self.nodes.len() * core::mem::size_of::<WideNode>()
            + self.nodes8.len() * core::mem::size_of::<WideNode8>()
            + self.packets.len() * core::mem::size_of::<TriPacket>()
    }
}

/// Collapse the validated, non-empty `bvh` into a `W`-wide tree: each wide node takes its BVH2
/// node's two children and repeatedly opens the inner child of largest surface area until it
/// has `W` children or only leaves. `leaf(n)` gives the child code of BVH2 leaf `n` (called
/// once per leaf, in depth-first order). Returns the nodes (depth-first pre-order) and depth.
fn collapse<const W: usize>(
    bvh: &Bvh,
    pad: f32,
    mut leaf: impl FnMut(u32) -> u32,
) -> Result<(Vec<WideNodeN<W>>, usize), TraceError> {
    let half_area = |b: &Aabb| {
        let e = b.max - b.min;
        e.x * e.y + e.y * e.z + e.z * e.x
    };
    let mut nodes: Vec<WideNodeN<W>> = Vec::with_capacity(bvh.nodes.len() / (W / 2) + 1);
    let mut max_depth = 0;
    let root = &bvh.nodes[bvh.root as usize];
    nodes.push(WideNodeN::empty());
    if root.is_leaf() {
        let code = leaf(bvh.root);
        nodes[0].set(0, &root.bounds, code, pad);
        return Ok((nodes, 0));
    }
    // Work items: (BVH2 node, wide parent index, lane, depth of the new wide node).
    let mut work: Vec<(u32, usize, usize, usize)> = vec![(bvh.root, usize::MAX, 0, 0)];
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
        let node = &bvh.nodes[n2 as usize];
        let mut kids: Vec<u32> = vec![node.left(), node.right()];
        while kids.len() < W {
            let best = kids
                .iter()
                .enumerate()
                .filter(|(_, &k)| !bvh.nodes[k as usize].is_leaf())
                .map(|(i, &k)| (i, half_area(&bvh.nodes[k as usize].bounds)))
                .fold(None, |acc: Option<(usize, f32)>, (i, a)| match acc {
                    Some((_, ba)) if ba >= a => acc,
                    _ => Some((i, a)),
                });
            let Some((i, _)) = best else { break };
            let k = bvh.nodes[kids[i] as usize];
            kids[i] = k.left();
            kids.insert(i + 1, k.right());
        }
        // Leaves first (their triangles follow the parent), then inner children in order.
        let mut inner = Vec::with_capacity(W);
        for (lane, &k) in kids.iter().enumerate() {
            let kn = &bvh.nodes[k as usize];
            if kn.is_leaf() {
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

/// Append the triangle packets of BVH2 leaf `n` and return its child code.
fn emit_leaf(packets: &mut Vec<TriPacket>, bvh: &Bvh, n: u32, tris: &[[Vec3; 3]]) -> u32 {
    let leaf = &bvh.nodes[n as usize];
    let first = packets.len() as u32;
    let prims = &bvh.prim_indices[leaf.first() as usize..(leaf.first() + leaf.count()) as usize];
    let chunks = prims.chunks(WIDTH);
    let k = chunks.len();
    for (c, chunk) in chunks.enumerate() {
        let mut p = TriPacket {
            v: [[0.0; WIDTH]; 9],
            id: [0; WIDTH],
            count: chunk.len() as u32,
            last: (c + 1 == k) as u32,
            _pad: [0; 2],
        };
        for lane in 0..WIDTH {
            let id = chunk[lane.min(chunk.len() - 1)];
            let t = &tris[id as usize];
            for (j, vert) in t.iter().enumerate() {
                let a = vert.to_array();
                for (ax, &x) in a.iter().enumerate() {
                    p.v[3 * j + ax][lane] = x;
                }
            }
            p.id[lane] = id;
        }
        packets.push(p);
    }
    LEAF | first
}
