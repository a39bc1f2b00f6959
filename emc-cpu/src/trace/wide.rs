//! The tracer's acceleration structure: any validated BVH2 collapsed into a 4-wide BVH whose
//! child boxes are stored SoA (one SSE register per plane), nodes and triangles laid out in
//! depth-first order, with the depth bound that sizes every traversal stack checked here.

use emc_core::Aabb;
use glam::Vec3;

use crate::bvh::Bvh;
use crate::trace::TraceError;

/// Children per wide node. Four: one SSE register per slab plane, and SSE is part of the
/// x86-64 baseline, so one code path serves every x86-64 CPU without runtime dispatch (other
/// targets use the bit-identical scalar test). An 8-wide AVX2 layout is not implemented.
pub const WIDTH: usize = 4;

/// Deepest wide tree the traversal stacks can hold (root at depth 0).
pub const MAX_DEPTH: usize = 96;

/// Entries of a traversal stack. Popping a node of depth `d` leaves at most `(WIDTH − 1)·d`
/// waiting siblings and pushes at most `WIDTH` children: `(WIDTH − 1)·(MAX_DEPTH + 1) + 1`.
pub const STACK_CAPACITY: usize = (WIDTH - 1) * (MAX_DEPTH + 1) + 1;

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

/// One 4-wide node: 128 bytes, two cache lines, 64-byte aligned.
///
/// ```text
///   bytes   0..96 : lo[x], hi[x], lo[y], hi[y], lo[z], hi[z]   each [f32; 4], lane = child
///   bytes  96..112: child[4]  inner: node index | leaf: LEAF | first slot | EMPTY
///   bytes 112..128: padding
/// ```
/// An unused lane has the empty box (lo = +inf, hi = −inf), which no ray enters.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(64))]
pub struct WideNode {
    /// `planes[2a]` = child minima on axis `a`, `planes[2a + 1]` = child maxima.
    pub planes: [[f32; WIDTH]; 6],
    /// Child codes, see the type docs.
    pub child: [u32; WIDTH],
    _pad: [u32; 4],
}

const _: () = assert!(core::mem::size_of::<WideNode>() == 128);

impl WideNode {
    /// A node with every lane unused.
    pub fn empty() -> WideNode {
        let mut planes = [[0.0; WIDTH]; 6];
        for a in 0..3 {
            planes[2 * a] = [f32::INFINITY; WIDTH];
            planes[2 * a + 1] = [f32::NEG_INFINITY; WIDTH];
        }
        WideNode {
            planes,
            child: [EMPTY; WIDTH],
            _pad: [0; 4],
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

/// A 4-wide BVH over a triangle list, ready to trace.
#[derive(Clone, Debug)]
pub struct WideBvh {
    /// Nodes in depth-first pre-order; node 0 is the root.
    pub nodes: Vec<WideNode>,
    /// Triangle packets in leaf order (a leaf's packets are contiguous).
    pub packets: Vec<TriPacket>,
    /// Number of triangles.
    pub triangles: usize,
    /// Largest absolute vertex coordinate (sizes the traversal's absolute culling slack).
    pub max_abs: f32,
    /// Depth of the wide tree (root alone: 0); at most [`MAX_DEPTH`].
    pub depth: usize,
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
    /// of largest surface area until it has four children or only leaves.
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
        let half_area = |b: &Aabb| {
            let e = b.max - b.min;
            e.x * e.y + e.y * e.z + e.z * e.x
        };
        let mut out = WideBvh {
            nodes: Vec::with_capacity(bvh.nodes.len() / 2 + 1),
            packets: Vec::with_capacity(tris.len() / 2),
            triangles: tris.len(),
            max_abs: aabbs.iter().fold(0.0f32, |m, b| {
                m.max(b.min.abs().max_element())
                    .max(b.max.abs().max_element())
            }),
            depth: 0,
            leaves: 0,
        };
        // Work items: (BVH2 node, wide parent index, lane, depth of the new wide node).
        // Child boxes are padded by 2^-16 of the largest coordinate: the triangle test rounds
        // `vertex − origin` to ulps of the coordinates, so with needles thinner than an ulp it
        // can report a hit a hair outside the exact box; the pad (2^7 ulps) keeps such hits
        // inside. It covers origins no farther from 0 than the geometry (then |o| ≤ M).
        let pad = out.max_abs * (1.0 / 65536.0);
        let mut work: Vec<(u32, usize, usize, usize)> = Vec::new();
        let root = &bvh.nodes[bvh.root as usize];
        out.nodes.push(WideNode::empty());
        if root.is_leaf() {
            let code = out.emit_leaf(bvh, bvh.root, tris);
            out.nodes[0].set(0, &root.bounds, code, pad);
            return Ok(out);
        }
        work.push((bvh.root, usize::MAX, 0, 0));
        while let Some((n2, parent, lane, depth)) = work.pop() {
            if depth > MAX_DEPTH {
                return Err(TraceError::TooDeep {
                    depth,
                    max: MAX_DEPTH,
                });
            }
            out.depth = out.depth.max(depth);
            let me = if parent == usize::MAX {
                0
            } else {
                let i = out.nodes.len();
                out.nodes.push(WideNode::empty());
                out.nodes[parent].child[lane] = i as u32;
                i
            };
            let node = &bvh.nodes[n2 as usize];
            let mut kids: Vec<u32> = vec![node.left(), node.right()];
            while kids.len() < WIDTH {
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
            let mut inner = Vec::with_capacity(WIDTH);
            for (lane, &k) in kids.iter().enumerate() {
                let kn = &bvh.nodes[k as usize];
                if kn.is_leaf() {
                    let code = out.emit_leaf(bvh, k, tris);
                    out.nodes[me].set(lane, &kn.bounds, code, pad);
                } else {
                    out.nodes[me].set(lane, &kn.bounds, EMPTY, pad);
                    inner.push((k, lane));
                }
            }
            for &(k, lane) in inner.iter().rev() {
                work.push((k, me, lane, depth + 1));
            }
        }
        Ok(out)
    }

    fn emit_leaf(&mut self, bvh: &Bvh, n: u32, tris: &[[Vec3; 3]]) -> u32 {
        let leaf = &bvh.nodes[n as usize];
        let first = self.packets.len() as u32;
        let prims =
            &bvh.prim_indices[leaf.first() as usize..(leaf.first() + leaf.count()) as usize];
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
            self.packets.push(p);
        }
        self.leaves += 1;
        LEAF | first
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// Bytes of nodes and triangle data.
    pub fn memory_bytes(&self) -> usize {
        self.nodes.len() * core::mem::size_of::<WideNode>()
            + self.packets.len() * core::mem::size_of::<TriPacket>()
    }
}
