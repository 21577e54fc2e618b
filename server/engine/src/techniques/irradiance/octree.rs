//! The multi-reference octree that holds `irradiance`'s cache entries (the paper's §4.4, after
//! Křivánek & Gautron): an entry is referenced by every node of one level that its zone's
//! bounding box overlaps: the deepest level at which that is at most `MAX_REFERENCES` nodes
//! (at least the level whose nodes are as wide as the box, so eight nodes at most there). A
//! long thin zone thus goes to finer nodes than its length alone would put it in, and lookups
//! far from it along its short axes do not test it. A lookup visits one node per level, from the root down to the deepest node
//! holding the point, and tests every entry referenced there: each entry at most once, and
//! every entry whose box holds the point. Nodes are created where entries are stored, so the
//! tree is finest where the cache is densest; the deepest node on a point's branch is the lock
//! of object-space locking (§5.1). Nodes are never removed or renumbered while the cache lives
//! (a pending request holds its node's index); `clear_references` keeps them.
//!
//! Built on the CPU (the paper rebuilds its octree from scratch at intervals too) and uploaded
//! in the layout `cache_lookup` in shaders/irradiance_common.wgsl reads.

/// Levels of the tree at most (MAX_DEPTH in irradiance/common.wgsl).
pub const MAX_DEPTH: u32 = 16;

/// Nodes one entry is referenced from at most (beyond the level its widest extent fits).
pub const MAX_REFERENCES: usize = 32;

#[derive(Debug, Clone)]
struct Node {
    /// Index of the first of its eight children (0: a leaf; the root is never a child).
    first_child: u32,
    depth: u32,
    references: Vec<u32>,
}

#[derive(Debug, Clone)]
pub struct Octree {
    root_min: [f32; 3],
    root_edge: f32,
    max_depth: u32,
    nodes: Vec<Node>,
    references: usize,
}

impl Octree {
    /// A tree over the cube at `root_min` with edge `root_edge`, complete down to `min_depth`
    /// (so object-space locking starts with 8^min_depth locks), at most `max_depth` deep.
    pub fn new(root_min: [f32; 3], root_edge: f32, min_depth: u32, max_depth: u32) -> Self {
        let max_depth = max_depth.clamp(1, MAX_DEPTH - 1);
        let mut tree = Self {
            root_min,
            root_edge,
            max_depth,
            nodes: vec![Node {
                first_child: 0,
                depth: 0,
                references: Vec::new(),
            }],
            references: 0,
        };
        let mut level = vec![0u32];
        for _ in 0..min_depth.min(max_depth) {
            let mut next = Vec::with_capacity(level.len() * 8);
            for node in level {
                let first = tree.subdivide(node);
                next.extend(first..first + 8);
            }
            level = next;
        }
        tree
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    pub fn reference_count(&self) -> usize {
        self.references
    }

    /// Most nodes one `insert` can create.
    pub fn max_new_nodes_per_insert(&self) -> usize {
        8 * MAX_REFERENCES * self.max_depth as usize
    }

    fn subdivide(&mut self, node: u32) -> u32 {
        let first = self.nodes.len() as u32;
        let depth = self.nodes[node as usize].depth + 1;
        self.nodes.extend((0..8).map(|_| Node {
            first_child: 0,
            depth,
            references: Vec::new(),
        }));
        self.nodes[node as usize].first_child = first;
        first
    }

    /// The level an entry whose bounding box has these half extents is stored at.
    pub fn level_for(&self, half_extent: [f32; 3]) -> u32 {
        let widest = 2.0 * half_extent.iter().fold(0.0f32, |a, &b| a.max(b));
        if widest.is_nan() || widest <= 0.0 {
            return self.max_depth;
        }
        let levels = (self.root_edge / widest).log2().floor();
        if levels <= 0.0 {
            0
        } else {
            (levels as u32).min(self.max_depth)
        }
    }

    /// The nodes of `level` the box `centre ± half_extent` overlaps, per axis.
    fn overlapped(
        &self,
        level: u32,
        centre: [f32; 3],
        half_extent: [f32; 3],
    ) -> [std::ops::RangeInclusive<u32>; 3] {
        let cells = 1u32 << level;
        let edge = self.root_edge / cells as f32;
        std::array::from_fn(|k| {
            let index = |x: f32| {
                let i = ((x - self.root_min[k]) / edge).floor();
                i.clamp(0.0, (cells - 1) as f32) as u32
            };
            index(centre[k] - half_extent[k])..=index(centre[k] + half_extent[k])
        })
    }

    /// References `entry` (whose zone lies within the box `centre ± half_extent`) from every
    /// node of its level that the box overlaps, creating the nodes it needs. Returns the
    /// references made.
    pub fn insert(&mut self, entry: u32, centre: [f32; 3], half_extent: [f32; 3]) -> usize {
        let count = |r: &[std::ops::RangeInclusive<u32>; 3]| {
            r.iter().map(|a| a.clone().count()).product::<usize>()
        };
        let mut level = self.level_for(half_extent);
        while level < self.max_depth
            && count(&self.overlapped(level + 1, centre, half_extent)) <= MAX_REFERENCES
        {
            level += 1;
        }
        let [xs, ys, zs] = self.overlapped(level, centre, half_extent);
        let mut made = 0;
        for z in zs {
            for y in ys.clone() {
                for x in xs.clone() {
                    let node = self.node_at_level([x, y, z], level);
                    self.nodes[node as usize].references.push(entry);
                    made += 1;
                }
            }
        }
        self.references += made;
        made
    }

    /// The node at `level` with integer coordinates `cell` there, created if needed.
    fn node_at_level(&mut self, cell: [u32; 3], level: u32) -> u32 {
        let mut node = 0u32;
        for depth in 0..level {
            let shift = level - 1 - depth;
            let octant = ((cell[0] >> shift) & 1)
                | ((cell[1] >> shift) & 1) << 1
                | ((cell[2] >> shift) & 1) << 2;
            let mut first = self.nodes[node as usize].first_child;
            if first == 0 {
                first = self.subdivide(node);
            }
            node = first + octant;
        }
        node
    }

    /// Drops every reference; the nodes stay.
    pub fn clear_references(&mut self) {
        for node in &mut self.nodes {
            node.references.clear();
        }
        self.references = 0;
    }

    /// The nodes a lookup at `p` visits, root first.
    pub fn branch(&self, p: [f32; 3]) -> Vec<u32> {
        let mut node = 0u32;
        let mut lo = self.root_min;
        let mut edge = self.root_edge;
        let mut branch = vec![0];
        loop {
            let first = self.nodes[node as usize].first_child;
            if first == 0 {
                return branch;
            }
            edge *= 0.5;
            let mut octant = 0;
            for k in 0..3 {
                if p[k] >= lo[k] + edge {
                    octant |= 1 << k;
                    lo[k] += edge;
                }
            }
            node = first + octant;
            branch.push(node);
        }
    }

    /// Every entry a lookup at `p` tests, in the order the GPU tests them.
    pub fn candidates(&self, p: [f32; 3]) -> Vec<u32> {
        self.branch(p)
            .into_iter()
            .flat_map(|n| self.nodes[n as usize].references.iter().copied())
            .collect()
    }

    /// The flattened tree: per node (first child, first reference, references, depth), then
    /// every node's references in node order. Returns the words and the references' offset.
    pub fn flatten(&self) -> (Vec<u32>, u32) {
        let refs_offset = 4 * self.nodes.len();
        let mut words = Vec::with_capacity(refs_offset + self.references);
        let mut first = 0u32;
        for node in &self.nodes {
            let count = node.references.len() as u32;
            words.extend([node.first_child, first, count, node.depth]);
            first += count;
        }
        for node in &self.nodes {
            words.extend_from_slice(&node.references);
        }
        (words, refs_offset as u32)
    }
}

/// Half extents of the axis-aligned box around an entry's zone: the local frame's axes
/// (`axes[i]`, unit vectors) scaled by the larger radius of each axis' two halves.
pub fn zone_half_extent(axes: [[f32; 3]; 3], radii: [f32; 6]) -> [f32; 3] {
    let reach = [
        radii[0].max(radii[1]),
        radii[2].max(radii[3]),
        radii[4].max(radii[5]),
    ];
    std::array::from_fn(|k| (0..3).map(|i| axes[i][k].abs() * reach[i]).sum())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tree() -> Octree {
        Octree::new([-0.5; 3], 1.0, 2, 10)
    }

    #[test]
    fn starts_complete_to_the_minimum_depth() {
        let t = tree();
        assert_eq!(t.node_count(), 1 + 8 + 64);
        assert_eq!(t.branch([0.1, 0.2, 0.3]).len(), 3);
    }

    #[test]
    fn an_entry_goes_to_the_deepest_level_with_few_enough_nodes() {
        let t = tree();
        // A box 0.1 wide fits nodes of edge 1/8 (level 3), not 1/16.
        assert_eq!(t.level_for([0.05; 3]), 3);
        // A cube 0.1 wide on a node corner: 8 nodes of edge 1/16 would still do (level 4), 64 of
        // 1/32 not.
        let mut t = tree();
        assert_eq!(t.insert(0, [0.0, 0.0, 0.0], [0.05; 3]), 8);
        assert_eq!(t.branch([0.01, 0.01, 0.01]).len(), 5);
        // A long thin zone goes deeper than its length alone would put it.
        let mut t = tree();
        let made = t.insert(1, [0.1, 0.1, 0.1], [0.2, 0.004, 0.004]);
        assert!((1..=MAX_REFERENCES).contains(&made));
        assert!(t.branch([0.1, 0.1, 0.1]).len() > t.level_for([0.2, 0.004, 0.004]) as usize + 1);
    }

    #[test]
    fn lookups_find_every_entry_whose_box_holds_the_point_and_each_once() {
        let mut t = tree();
        let mut boxes = Vec::new();
        let mut seed = 12345u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        for i in 0..300 {
            let centre = [next() - 0.5, next() - 0.5, next() - 0.5];
            let h = 0.002 + 0.2 * next() * next();
            let half = [h, h * (0.3 + next()), h * (0.3 + next())];
            t.insert(i, centre, half);
            boxes.push((centre, half));
        }
        for _ in 0..2000 {
            let p = [next() - 0.5, next() - 0.5, next() - 0.5];
            let found = t.candidates(p);
            let mut sorted = found.clone();
            sorted.sort_unstable();
            sorted.dedup();
            assert_eq!(
                sorted.len(),
                found.len(),
                "an entry was tested twice at {p:?}"
            );
            for (i, (c, h)) in boxes.iter().enumerate() {
                let inside = (0..3).all(|k| (p[k] - c[k]).abs() < h[k]);
                if inside {
                    assert!(found.contains(&(i as u32)), "entry {i} missed at {p:?}");
                }
            }
        }
        // Small entries made the tree finer where they are.
        assert!(t.node_count() > 1 + 8 + 64);
    }

    #[test]
    fn clearing_references_keeps_the_node_numbering() {
        let mut t = tree();
        t.insert(0, [0.1, 0.1, 0.1], [0.001; 3]);
        let nodes = t.node_count();
        let deepest = *t.branch([0.1, 0.1, 0.1]).last().unwrap();
        t.clear_references();
        assert_eq!(t.reference_count(), 0);
        assert_eq!(t.node_count(), nodes);
        assert_eq!(*t.branch([0.1, 0.1, 0.1]).last().unwrap(), deepest);
    }

    #[test]
    fn flattened_layout_lists_each_nodes_references() {
        let mut t = tree();
        t.insert(3, [0.2, 0.2, 0.2], [0.01; 3]);
        t.insert(4, [-0.2, 0.2, 0.2], [0.3; 3]);
        let (words, refs_offset) = t.flatten();
        assert_eq!(refs_offset as usize, 4 * t.node_count());
        assert_eq!(words.len(), refs_offset as usize + t.reference_count());
        // Walk the flattened tree as the shader does.
        let p = [0.2, 0.2, 0.2];
        let mut node = 0usize;
        let mut lo = [-0.5f32; 3];
        let mut edge = 1.0f32;
        let mut seen = Vec::new();
        loop {
            let (child, first, count) = (words[4 * node], words[4 * node + 1], words[4 * node + 2]);
            for i in 0..count {
                seen.push(words[(refs_offset + first + i) as usize]);
            }
            if child == 0 {
                break;
            }
            edge *= 0.5;
            let mut octant = 0;
            for k in 0..3 {
                if p[k] >= lo[k] + edge {
                    octant |= 1 << k;
                    lo[k] += edge;
                }
            }
            node = (child + octant) as usize;
        }
        assert_eq!(seen, t.candidates(p));
        assert!(seen.contains(&3) && seen.contains(&4));
    }

    #[test]
    fn zone_boxes_follow_the_frame() {
        let axes = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(
            zone_half_extent(axes, [1.0, 2.0, 0.5, 0.25, 3.0, 1.0]),
            [2.0, 0.5, 3.0]
        );
        let s = std::f32::consts::FRAC_1_SQRT_2;
        let rotated = [[s, s, 0.0], [-s, s, 0.0], [0.0, 0.0, 1.0]];
        let h = zone_half_extent(rotated, [1.0; 6]);
        assert!((h[0] - 2.0 * s).abs() < 1e-6 && (h[2] - 1.0).abs() < 1e-6);
    }
}
