//! The flat BVH2 node layout every builder writes and every consumer reads: 32 bytes,
//! `#[repr(C)]`, two constructors, named accessors (no bit fiddling outside this file).
#![forbid(unsafe_code)]

use emc_core::Aabb;

/// Top bit of `b`: set for a leaf.
const LEAF_BIT: u32 = 1 << 31;

/// One node of a binary BVH.
///
/// ```text
///   bounds.min (12 B) | bounds.max (12 B) | a (4 B)           | b (4 B)
///   inner:                                  left child index  | right child index
///   leaf:                                   first prim slot   | LEAF_BIT | prim count
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Default)]
#[repr(C)]
pub struct Node {
    /// Bounds of everything below.
    pub bounds: Aabb,
    a: u32,
    b: u32,
}

const _: () = assert!(core::mem::size_of::<Node>() == 32);

impl Node {
    /// An inner node with two children (indices into the node array).
    #[inline]
    pub fn inner(bounds: Aabb, left: u32, right: u32) -> Node {
        debug_assert!(right & LEAF_BIT == 0);
        Node {
            bounds,
            a: left,
            b: right,
        }
    }

    /// A leaf holding `count` (≥ 1) primitives at `prim_indices[first..first + count]`.
    #[inline]
    pub fn leaf(bounds: Aabb, first: u32, count: u32) -> Node {
        debug_assert!(count >= 1 && count & LEAF_BIT == 0);
        Node {
            bounds,
            a: first,
            b: LEAF_BIT | count,
        }
    }

    /// The same node with both child links moved by `delta` (wrapping), a leaf unchanged: how
    /// a depth-first block is moved to another place in the node array. No branch.
    #[inline(always)]
    pub(crate) fn with_children_moved(self, delta: u32) -> Node {
        // All ones for an inner node, zero for a leaf.
        let inner = (self.b >> 31).wrapping_sub(1);
        let d = delta & inner;
        Node {
            bounds: self.bounds,
            a: self.a.wrapping_add(d),
            b: self.b.wrapping_add(d),
        }
    }

    /// True for a leaf.
    #[inline]
    pub fn is_leaf(&self) -> bool {
        self.b & LEAF_BIT != 0
    }

    /// Left child (inner nodes only).
    #[inline]
    pub fn left(&self) -> u32 {
        self.a
    }

    /// Right child (inner nodes only).
    #[inline]
    pub fn right(&self) -> u32 {
        self.b
    }

    /// First primitive slot (leaves only).
    #[inline]
    pub fn first(&self) -> u32 {
        self.a
    }

    /// Number of primitives (leaves only; 0 for inner nodes).
    #[inline]
    pub fn count(&self) -> u32 {
        if self.is_leaf() {
            self.b & !LEAF_BIT
        } else {
            0
        }
    }
}

/// A binary BVH: nodes, the primitive order the leaves index into, and the root.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Bvh {
    /// All nodes; children may sit anywhere in the array.
    pub nodes: Vec<Node>,
    /// Primitive ids in leaf order: leaf `l` holds `prim_indices[l.first()..l.first()+l.count()]`.
    pub prim_indices: Vec<u32>,
    /// Index of the root node.
    pub root: u32,
}

impl Bvh {
    /// This tree renumbered depth-first into `out` (its buffers reused): every node's left
    /// child right after it, the root at 0, and the leaves' primitives in the order the leaves
    /// are met. The same tree; a consumer that walks it depth-first then reads both arrays
    /// front to back instead of jumping where a restructuring pass (ATR rewrites treelets in
    /// place) left each subtree. `self` must be a valid tree.
    pub fn depth_first_into(&self, out: &mut Bvh) {
        self.depth_first_into_with(out, |_, _| {});
    }

    /// [`Bvh::depth_first_into`], calling `done(nodes, i)` for every new node `i` once its
    /// subtree is complete (children before parents): `nodes` is the copy so far, in which
    /// node `i` and everything below it are final. Work on the copy's nodes done here runs
    /// while the walk's scattered reads of `self` are in flight.
    pub fn depth_first_into_with(&self, out: &mut Bvh, mut done: impl FnMut(&[Node], u32)) {
        out.nodes.clear();
        out.nodes.reserve(self.nodes.len());
        out.prim_indices.clear();
        out.prim_indices.reserve(self.prim_indices.len());
        out.root = 0;
        if self.nodes.is_empty() {
            return;
        }
        // (old node, new index of the parent whose right link it fills; u32::MAX: none). A
        // stack-based pre-order: left children come off right after their parent.
        let mut stack: Vec<(u32, u32)> = Vec::with_capacity(64);
        // New inner nodes whose subtree is not complete, innermost last; the top bit is set
        // once the walk is in the right subtree.
        const RIGHT: u32 = 1 << 31;
        let mut open: Vec<u32> = Vec::with_capacity(64);
        stack.push((self.root, u32::MAX));
        while let Some((i, parent)) = stack.pop() {
            let here = out.nodes.len() as u32;
            if parent != u32::MAX {
                let p = &mut out.nodes[parent as usize];
                *p = Node::inner(p.bounds, p.left(), here);
                // The parent's left subtree is complete: it is the innermost open node.
                debug_assert_eq!(open.last(), Some(&parent));
                if let Some(top) = open.last_mut() {
                    *top |= RIGHT;
                }
            }
            let node = self.nodes[i as usize];
            if node.is_leaf() {
                let (f, c) = (node.first() as usize, node.count());
                let first = out.prim_indices.len() as u32;
                out.prim_indices
                    .extend_from_slice(&self.prim_indices[f..f + c as usize]);
                out.nodes.push(Node::leaf(node.bounds, first, c));
                done(&out.nodes, here);
                // Every open node whose right subtree this leaf ends is complete.
                while let Some(&top) = open.last() {
                    if top & RIGHT == 0 {
                        break;
                    }
                    open.pop();
                    done(&out.nodes, top & !RIGHT);
                }
            } else {
                // The right child is read long after this: fetch it now.
                crate::trace::traverse::prefetch(&self.nodes[node.right() as usize], 32);
                // Its right link is set when the right child comes off the stack.
                out.nodes.push(Node::inner(node.bounds, here + 1, 0));
                open.push(here);
                stack.push((node.right(), here));
                stack.push((node.left(), u32::MAX));
            }
        }
    }
}
