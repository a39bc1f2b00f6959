//! Structural check of any [`Bvh`] against the primitive boxes it was built from: every
//! primitive exactly once, exact `f32` containment, reachability, node count and depth.
//! Iterative, never panics: a malformed tree yields a [`ValidateError`] naming the node.
#![forbid(unsafe_code)]

use super::node::Bvh;
use emc_core::Aabb;

/// What [`Bvh::validate`] found on a well-formed tree.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BvhStats {
    /// Number of nodes (all reachable).
    pub nodes: usize,
    /// Number of inner nodes.
    pub inner: usize,
    /// Number of leaves.
    pub leaves: usize,
    /// Number of primitives.
    pub prims: usize,
    /// Largest number of primitives in one leaf.
    pub max_leaf_size: u32,
    /// Depth: edges on the longest root-to-leaf path (a lone root leaf has depth 0).
    pub depth: usize,
}

/// Why a BVH is malformed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ValidateError {
    /// The tree has no node although there are primitives (or nodes without primitives).
    #[error("the BVH has {nodes} nodes for {prims} primitives")]
    Empty {
        /// Nodes in the tree.
        nodes: usize,
        /// Primitives given.
        prims: usize,
    },
    /// The root index is outside the node array.
    #[error("root index {root} is outside the {nodes} nodes")]
    BadRoot {
        /// The root index.
        root: u32,
        /// Nodes in the tree.
        nodes: usize,
    },
    /// An inner node names a child outside the node array.
    #[error("node {node} has child index {child}, outside the {nodes} nodes")]
    BadChild {
        /// The inner node.
        node: u32,
        /// The child index it holds.
        child: u32,
        /// Nodes in the tree.
        nodes: usize,
    },
    /// A node is reached twice (a shared child or a cycle).
    #[error("node {node} is reached twice (shared child or cycle)")]
    Revisited {
        /// The node reached twice.
        node: u32,
    },
    /// Some nodes are not reachable from the root.
    #[error("{unreachable} of {nodes} nodes are not reachable from the root")]
    Unreachable {
        /// Number of unreachable nodes.
        unreachable: usize,
        /// Nodes in the tree.
        nodes: usize,
    },
    /// A child's box is not inside its parent's box.
    #[error("child {child} of node {node} is not inside its parent's box")]
    ChildOutside {
        /// The parent.
        node: u32,
        /// The child.
        child: u32,
    },
    /// A leaf's primitive range leaves the primitive index array (or is empty).
    #[error("leaf {node} holds slots {first}..{first}+{count}, outside the {slots} slots")]
    BadLeafRange {
        /// The leaf.
        node: u32,
        /// First slot.
        first: u32,
        /// Number of slots.
        count: u32,
        /// Length of the primitive index array.
        slots: usize,
    },
    /// A primitive index that is not a primitive.
    #[error("leaf {node} holds primitive {prim}, but there are only {prims} primitives")]
    BadPrim {
        /// The leaf.
        node: u32,
        /// The primitive index.
        prim: u32,
        /// Number of primitives.
        prims: usize,
    },
    /// A primitive held twice.
    #[error("primitive {prim} is held twice (again by leaf {node})")]
    DuplicatePrim {
        /// The primitive.
        prim: u32,
        /// The second leaf holding it.
        node: u32,
    },
    /// A primitive not held by any leaf (or a slot not referenced by any leaf).
    #[error("primitive {prim} is not held by any leaf")]
    MissingPrim {
        /// The primitive.
        prim: u32,
    },
    /// The primitive index array has the wrong length.
    #[error("the primitive index array has {slots} slots for {prims} primitives")]
    SlotCount {
        /// Length of the primitive index array.
        slots: usize,
        /// Number of primitives.
        prims: usize,
    },
    /// A leaf's box does not contain one of its primitives' boxes.
    #[error("leaf {node} does not contain the box of its primitive {prim}")]
    PrimOutside {
        /// The leaf.
        node: u32,
        /// The primitive.
        prim: u32,
    },
    /// The node count does not match a binary tree over its leaves.
    #[error(
        "{nodes} nodes but {leaves} leaves and {inner} inner nodes (expected inner = leaves - 1)"
    )]
    NodeCount {
        /// Nodes in the tree.
        nodes: usize,
        /// Leaves found.
        leaves: usize,
        /// Inner nodes found.
        inner: usize,
    },
}

impl Bvh {
    /// Check the tree against the boxes of the primitives it was built over (`aabbs[p]` is the box
    /// of primitive `p`). Containment is exact in `f32` (closed boxes). Returns the tree's
    /// statistics, or the first defect found. Runs in `O(nodes + prims)` with an explicit stack.
    pub fn validate(&self, aabbs: &[Aabb]) -> Result<BvhStats, ValidateError> {
        let nodes = self.nodes.len();
        let prims = aabbs.len();
        if nodes == 0 || prims == 0 {
            if nodes == 0 && prims == 0 && self.prim_indices.is_empty() {
                return Ok(BvhStats {
                    nodes: 0,
                    inner: 0,
                    leaves: 0,
                    prims: 0,
                    max_leaf_size: 0,
                    depth: 0,
                });
            }
            return Err(ValidateError::Empty { nodes, prims });
        }
        if self.prim_indices.len() != prims {
            return Err(ValidateError::SlotCount {
                slots: self.prim_indices.len(),
                prims,
            });
        }
        if self.root as usize >= nodes {
            return Err(ValidateError::BadRoot {
                root: self.root,
                nodes,
            });
        }
        let mut visited = vec![false; nodes];
        let mut held = vec![false; prims];
        let mut slot_used = vec![false; prims];
        let (mut inner, mut leaves, mut depth, mut max_leaf) = (0usize, 0usize, 0usize, 0u32);
        let mut stack: Vec<(u32, usize)> = vec![(self.root, 0)];
        while let Some((i, d)) = stack.pop() {
            if std::mem::replace(&mut visited[i as usize], true) {
                return Err(ValidateError::Revisited { node: i });
            }
            let node = &self.nodes[i as usize];
            if node.is_leaf() {
                leaves += 1;
                depth = depth.max(d);
                let (first, count) = (node.first(), node.count());
                max_leaf = max_leaf.max(count);
                let end = first as u64 + count as u64;
                if count == 0 || end > prims as u64 {
                    return Err(ValidateError::BadLeafRange {
                        node: i,
                        first,
                        count,
                        slots: prims,
                    });
                }
                let range = first as usize..end as usize;
                for (used, &p) in slot_used[range.clone()]
                    .iter_mut()
                    .zip(&self.prim_indices[range])
                {
                    if std::mem::replace(used, true) {
                        // Two leaves share a slot, so that slot's primitive is held twice.
                        return Err(ValidateError::DuplicatePrim { prim: p, node: i });
                    }
                    let Some(b) = aabbs.get(p as usize) else {
                        return Err(ValidateError::BadPrim {
                            node: i,
                            prim: p,
                            prims,
                        });
                    };
                    if std::mem::replace(&mut held[p as usize], true) {
                        return Err(ValidateError::DuplicatePrim { prim: p, node: i });
                    }
                    if !node.bounds.contains(b) {
                        return Err(ValidateError::PrimOutside { node: i, prim: p });
                    }
                }
            } else {
                inner += 1;
                for c in [node.left(), node.right()] {
                    let Some(child) = self.nodes.get(c as usize) else {
                        return Err(ValidateError::BadChild {
                            node: i,
                            child: c,
                            nodes,
                        });
                    };
                    if !node.bounds.contains(&child.bounds) {
                        return Err(ValidateError::ChildOutside { node: i, child: c });
                    }
                }
                stack.push((node.right(), d + 1));
                stack.push((node.left(), d + 1));
            }
        }
        let reached = inner + leaves;
        if reached != nodes {
            return Err(ValidateError::Unreachable {
                unreachable: nodes - reached,
                nodes,
            });
        }
        if let Some(p) = held.iter().position(|&h| !h) {
            return Err(ValidateError::MissingPrim { prim: p as u32 });
        }
        if inner + 1 != leaves {
            return Err(ValidateError::NodeCount {
                nodes,
                leaves,
                inner,
            });
        }
        Ok(BvhStats {
            nodes,
            inner,
            leaves,
            prims,
            max_leaf_size: max_leaf,
            depth,
        })
    }

    /// Depth of the tree (edges on the longest root-to-leaf path), by an iterative walk that
    /// visits each node once; 0 for an empty tree or a malformed root.
    pub fn depth(&self) -> usize {
        let n = self.nodes.len();
        if self.root as usize >= n {
            return 0;
        }
        let mut seen = vec![false; n];
        let mut stack = vec![(self.root, 0usize)];
        let mut depth = 0;
        while let Some((i, d)) = stack.pop() {
            let Some(node) = self.nodes.get(i as usize) else {
                continue;
            };
            if std::mem::replace(&mut seen[i as usize], true) {
                continue;
            }
            if node.is_leaf() {
                depth = depth.max(d);
            } else {
                stack.push((node.left(), d + 1));
                stack.push((node.right(), d + 1));
            }
        }
        depth
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::node::Node;
    use glam::Vec3;

    fn bx(lo: f32, hi: f32) -> Aabb {
        Aabb::new(Vec3::splat(lo), Vec3::splat(hi))
    }

    fn good() -> (Bvh, Vec<Aabb>) {
        let prims = vec![bx(0.0, 1.0), bx(2.0, 3.0), bx(1.0, 2.0)];
        let bvh = Bvh {
            nodes: vec![
                Node::inner(bx(0.0, 3.0), 1, 2),
                Node::leaf(bx(0.0, 2.0), 0, 2),
                Node::leaf(bx(2.0, 3.0), 2, 1),
            ],
            prim_indices: vec![0, 2, 1],
            root: 0,
        };
        (bvh, prims)
    }

    #[test]
    fn accepts_good_tree() {
        let (bvh, prims) = good();
        let s = bvh.validate(&prims).unwrap();
        assert_eq!((s.nodes, s.leaves, s.depth, s.max_leaf_size), (3, 2, 1, 2));
        assert_eq!(bvh.depth(), 1);
    }

    #[test]
    fn rejects_each_defect() {
        let (bvh, prims) = good();
        let mut b = bvh.clone();
        b.nodes[2].bounds = bx(2.0, 3.5);
        assert_eq!(
            b.validate(&prims),
            Err(ValidateError::ChildOutside { node: 0, child: 2 })
        );
        let mut b = bvh.clone();
        b.prim_indices = vec![0, 2, 2];
        assert!(matches!(
            b.validate(&prims),
            Err(ValidateError::DuplicatePrim { prim: 2, .. })
        ));
        let mut b = bvh.clone();
        b.nodes[1] = Node::leaf(bx(0.0, 1.5), 0, 2);
        b.nodes[0].bounds = bx(0.0, 3.0);
        assert!(matches!(
            b.validate(&prims),
            Err(ValidateError::PrimOutside { prim: 2, .. })
        ));
        let mut b = bvh.clone();
        b.nodes[0] = Node::inner(bx(0.0, 3.0), 1, 1);
        assert_eq!(
            b.validate(&prims),
            Err(ValidateError::Revisited { node: 1 })
        );
        let mut b = bvh.clone();
        b.nodes[0] = Node::inner(bx(0.0, 3.0), 1, 7);
        assert!(matches!(
            b.validate(&prims),
            Err(ValidateError::BadChild { .. })
        ));
        let mut b = bvh.clone();
        b.nodes.push(Node::leaf(bx(0.0, 1.0), 0, 1));
        assert!(b.validate(&prims).is_err());
        let mut b = bvh.clone();
        b.root = 9;
        assert!(matches!(
            b.validate(&prims),
            Err(ValidateError::BadRoot { .. })
        ));
        let mut b = bvh.clone();
        b.nodes[2] = Node::leaf(bx(2.0, 3.0), 2, 5);
        assert!(matches!(
            b.validate(&prims),
            Err(ValidateError::BadLeafRange { .. })
        ));
        assert!(bvh.validate(&prims[..2]).is_err());
    }
}
