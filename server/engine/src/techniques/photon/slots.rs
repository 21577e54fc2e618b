//! Where a photon path's records live (photon/trace.wgsl, `record_slot`), on the host: for
//! the buffers' sizes, and to read a map back in an order that does not depend on which
//! chunks the paths happened to take.
//!
//! - Each pass owns a block of `photons_per_pass · path_slots` slots: first `inline_slots` per
//!   path (its first interactions), then a pool of chunks of `CHUNK_SLOTS` slots.
//! - A path that grows past its inline slots takes chunks from its pass's pool (an atomic
//!   count), linked from `PhotonPath::chunk` through the next pointers of the `chunks` buffer.
//! - An update keeps a path's chunks and takes more only where the path grows, so the slots
//!   of an incrementally updated map differ from a full recompute's, but every path holds the
//!   same records in the same order, and the gather's fixed-point sums do not depend on where
//!   a record lies. `canonical` gives that order.

use crate::techniques::photon::gpu::{CHUNK_NONE, CHUNK_SLOTS, PhotonPath};

/// The record slots' layout of one session (`PhotonUniforms::path_slots` and the rest).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecordLayout {
    pub photons_per_pass: u32,
    /// Slots per path on average (its inline ones and its pass's pool's share).
    pub path_slots: u32,
    pub inline_slots: u32,
    pub chunks_per_pass: u32,
}

/// A path's own slots where it takes chunks: most paths end before them.
pub const INLINE_SLOTS: u32 = 4;

impl RecordLayout {
    /// Paths of at most `bounces` interactions in `record_slots` slots each on average: all
    /// their own where that holds the cap, else `INLINE_SLOTS` and the rest in chunks.
    pub fn new(photons_per_pass: u32, bounces: u32, record_slots: u32) -> Self {
        if bounces <= record_slots {
            return Self {
                photons_per_pass,
                path_slots: bounces,
                inline_slots: bounces,
                chunks_per_pass: 0,
            };
        }
        let inline_slots = INLINE_SLOTS.min(record_slots);
        let pool = (record_slots - inline_slots) / CHUNK_SLOTS * CHUNK_SLOTS;
        Self {
            photons_per_pass,
            path_slots: inline_slots + pool,
            inline_slots,
            chunks_per_pass: photons_per_pass * (pool / CHUNK_SLOTS),
        }
    }

    fn block(&self, path: u32) -> u32 {
        path / self.photons_per_pass * self.photons_per_pass * self.path_slots
    }

    /// Slots one pass's pool holds.
    pub fn pool_slots(&self) -> u32 {
        self.photons_per_pass * (self.path_slots - self.inline_slots)
    }

    /// Path `path`'s slot for its interaction `k` < `inline_slots`.
    pub fn inline_slot(&self, path: u32, k: u32) -> u32 {
        self.block(path) + path % self.photons_per_pass * self.inline_slots + k
    }

    /// Slot `j` of chunk `chunk` (its index in the pool of `path`'s pass).
    pub fn chunk_slot(&self, path: u32, chunk: u32, j: u32) -> u32 {
        self.block(path) + self.photons_per_pass * self.inline_slots + chunk * CHUNK_SLOTS + j
    }

    /// The word of `chunk`'s next pointer in the `chunks` buffer.
    pub fn chunk_word(&self, path: u32, chunk: u32) -> usize {
        (path / self.photons_per_pass) as usize * self.chunks_per_pass as usize + chunk as usize
    }

    /// The slots of `path`'s records in order (`count` of them), following its chunk list
    /// through `next` (the `chunks` buffer's next pointers). None where the list is shorter
    /// than the count or leaves the pool: a map the trace did not write.
    pub fn path_record_slots(&self, path: u32, p: &PhotonPath, next: &[u32]) -> Option<Vec<u32>> {
        let mut slots = Vec::with_capacity(p.count as usize);
        let mut chunk = CHUNK_NONE;
        for k in 0..p.count {
            if k < self.inline_slots {
                slots.push(self.inline_slot(path, k));
                continue;
            }
            let j = (k - self.inline_slots) % CHUNK_SLOTS;
            if j == 0 {
                chunk = if k == self.inline_slots {
                    p.chunk
                } else {
                    *next.get(self.chunk_word(path, chunk))?
                };
                if chunk >= self.chunks_per_pass {
                    return None;
                }
            }
            slots.push(self.chunk_slot(path, chunk, j));
        }
        Some(slots)
    }
}

/// A map in path order: every path's record slots one after the other (`slots`), and where
/// each slot's record stands in that order (`index_of`, `u32::MAX` for slots that hold none).
#[derive(Debug, Clone, PartialEq)]
pub struct Canonical {
    pub slots: Vec<u32>,
    /// First entry of each path in `slots` (one more than paths: the end).
    pub path_starts: Vec<usize>,
    pub index_of: Vec<u32>,
}

/// The path order of `paths`' records among `record_slots` slots (`RecordLayout`).
pub fn canonical(
    layout: &RecordLayout,
    paths: &[PhotonPath],
    next: &[u32],
    record_slots: usize,
) -> Option<Canonical> {
    let mut slots = Vec::new();
    let mut path_starts = Vec::with_capacity(paths.len() + 1);
    let mut index_of = vec![u32::MAX; record_slots];
    for (i, p) in paths.iter().enumerate() {
        path_starts.push(slots.len());
        for slot in layout.path_record_slots(i as u32, p, next)? {
            *index_of.get_mut(slot as usize)? = slots.len() as u32;
            slots.push(slot);
        }
    }
    path_starts.push(slots.len());
    Some(Canonical {
        slots,
        path_starts,
        index_of,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path(count: u32, chunk: u32) -> PhotonPath {
        PhotonPath {
            count,
            chunk,
            ..bytemuck::Zeroable::zeroed()
        }
    }

    #[test]
    fn short_caps_keep_every_slot_inline() {
        let l = RecordLayout::new(10, 3, 16);
        assert_eq!((l.path_slots, l.inline_slots, l.chunks_per_pass), (3, 3, 0));
        assert_eq!(l.inline_slot(12, 2), 10 * 3 + 2 * 3 + 2);
        assert_eq!(l.pool_slots(), 0);
    }

    #[test]
    fn long_caps_share_a_pool_of_chunks_per_pass() {
        // 16 slots a path: 4 inline, 12 in chunks (3 a path on average).
        let l = RecordLayout::new(10, 256, 16);
        assert_eq!(
            (l.path_slots, l.inline_slots, l.chunks_per_pass),
            (16, 4, 30)
        );
        assert_eq!(l.pool_slots(), 120);
        // Pass 1's block starts at 160; its inline slots take 40, then the pool.
        assert_eq!(l.inline_slot(11, 3), 160 + 4 + 3);
        assert_eq!(l.chunk_slot(11, 2, 1), 160 + 40 + 8 + 1);
        assert_eq!(l.chunk_word(11, 2), 30 + 2);
        // A pool that is not a whole number of chunks is rounded down.
        let odd = RecordLayout::new(10, 64, 11);
        assert_eq!((odd.path_slots, odd.chunks_per_pass), (8, 10));
    }

    #[test]
    fn a_path_follows_its_chunk_list() {
        let l = RecordLayout::new(10, 256, 16);
        // Path 3 (pass 0) holds 10 records: 4 inline, then chunk 5, then chunk 2.
        let mut next = vec![CHUNK_NONE; 2 * 30];
        next[5] = 2;
        let slots = l.path_record_slots(3, &path(10, 5), &next).expect("slots");
        let pool = 40;
        assert_eq!(
            slots,
            vec![
                12,
                13,
                14,
                15,
                pool + 20,
                pool + 21,
                pool + 22,
                pool + 23,
                pool + 8,
                pool + 9
            ]
        );
        // A list that ends too early is a map the trace did not write.
        assert_eq!(l.path_record_slots(3, &path(13, 5), &next), None);
        assert_eq!(l.path_record_slots(3, &path(6, CHUNK_NONE), &next), None);
    }

    #[test]
    fn the_canonical_order_does_not_depend_on_which_chunks_paths_took() {
        let l = RecordLayout::new(2, 256, 8);
        assert_eq!(l.chunks_per_pass, 2);
        // Path 0 holds 6 records, path 1 two; in `a` path 0 took chunk 0, in `b` chunk 1.
        let a = [path(6, 0), path(2, CHUNK_NONE)];
        let b = [path(6, 1), path(2, CHUNK_NONE)];
        let next = vec![CHUNK_NONE; 2];
        let ca = canonical(&l, &a, &next, 16).expect("a");
        let cb = canonical(&l, &b, &next, 16).expect("b");
        assert_eq!(ca.path_starts, vec![0, 6, 8]);
        assert_eq!(cb.path_starts, ca.path_starts);
        assert_eq!(ca.slots[4..], [8, 9, 4, 5]);
        assert_eq!(cb.slots[4..], [12, 13, 4, 5]);
        assert_eq!((ca.index_of[8], cb.index_of[8]), (4, u32::MAX));
        assert_eq!(
            ca.index_of[6],
            u32::MAX,
            "path 1's third inline slot holds nothing"
        );
    }
}
