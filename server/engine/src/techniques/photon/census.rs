//! The work census of technique `photon` (beyond the paper): how much of a full recompute any
//! bit-exact incremental update between two TFs must redo, counted per record by
//! `Photon::census` and compared here, path by path.
//!
//! The bound rests on two facts of the exact update (docs/architecture.md, `photon`):
//! - A segment's radiance is a sum of 64-bit fixed-point terms, each truncated on its own,
//!   so a changed record's new term at a lattice sample cannot be had by rescaling an old
//!   sum: every term a changed record gives the new gather must be formed.
//! - A record that moved (position, direction or existence) needs its flight tracked
//!   again. Where the opacity only fell, the tentative collisions before the old collision
//!   stay rejected, so at best the tracking resumes from the old collision; where it rose,
//!   it must start earlier. Counting from the old collision is therefore a lower bound.
//!
//! Everything else an update does (listing, marking, grids, subtracting old terms,
//! compositing) is left out, and a term or a step is taken to cost what it does in the full
//! recompute: the bound is optimistic for the update.

use crate::techniques::photon::gpu::PhotonRecord;

/// A full recompute's work per record (`Photon::census`), the records in path order.
#[derive(Debug, Clone, PartialEq)]
pub struct Census {
    /// Gather terms each record gave (lattice samples within the radius that take photons).
    pub terms: Vec<u32>,
    /// Tracking steps (tentative collisions) of the flight that stored each record.
    pub steps: Vec<u32>,
    pub records: Vec<PhotonRecord>,
    /// Each path's first record, then the end (one more than paths).
    pub path_starts: Vec<usize>,
    /// Per path, the tracking steps of its last flight, which stored no record (it left the
    /// volume; 0 where the path ended otherwise).
    pub end_steps: Vec<u32>,
}

/// Interaction `k` of one path in a census: its record (an empty one past the path's end),
/// its terms and the steps of the flight that ended there (the last flight's at the end).
struct Slot {
    record: PhotonRecord,
    terms: u32,
    steps: u32,
}

impl Census {
    fn paths(&self) -> usize {
        self.path_starts.len().saturating_sub(1)
    }

    /// Records path `path` holds.
    fn count(&self, path: usize) -> usize {
        self.path_starts[path + 1] - self.path_starts[path]
    }

    fn slot(&self, path: usize, k: usize) -> Slot {
        let count = self.count(path);
        if k < count {
            let i = self.path_starts[path] + k;
            return Slot {
                record: self.records[i],
                terms: self.terms[i],
                steps: self.steps[i],
            };
        }
        Slot {
            record: EMPTY,
            terms: 0,
            steps: if k == count { self.end_steps[path] } else { 0 },
        }
    }
}

/// A slot that holds no photon (`CELL_NONE`).
const EMPTY: PhotonRecord = PhotonRecord {
    position: [0.0; 3],
    cell: u32::MAX,
    power: [0.0; 3],
    hist_lo: 0,
    direction: [0.0; 3],
    hist_hi: 0,
};

/// The least work of any bit-exact update from one TF's photon map to another's, next to the
/// second TF's full recompute (`WorkBound::between`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct WorkBound {
    /// Records compared: per path the more of its two versions' records.
    pub records: u64,
    /// Records that differ (or exist in one version only).
    pub records_changed: u64,
    /// Of those, records whose position and direction are the same (only the power differs).
    pub records_power_only: u64,
    pub paths: u64,
    /// Paths with a record whose position, direction or existence changed.
    pub paths_moved: u64,
    /// Terms of the new full gather, and those of the changed records' new versions (which
    /// every exact update forms).
    pub terms: u64,
    pub terms_changed: u64,
    /// Terms the old versions of moved or removed records gave the old gather (an update
    /// subtracts them or gathers afresh where they were; not in the bound).
    pub terms_moved_old: u64,
    /// Tracking steps of the new full trace; of the flights from each moved path's first
    /// moved slot on; and the same with that first flight counted only past the old flight's
    /// steps (the lower bound).
    pub steps: u64,
    pub steps_retracked: u64,
    pub steps_resumed: u64,
}

fn same_place(a: &PhotonRecord, b: &PhotonRecord) -> bool {
    a.position == b.position && a.direction == b.direction && a.cell == b.cell
}

impl WorkBound {
    /// Compares the censuses of the same map under two TFs.
    pub fn between(old: &Census, new: &Census) -> WorkBound {
        let paths = new.paths().min(old.paths());
        let mut bound = WorkBound {
            paths: paths as u64,
            terms: new.terms.iter().map(|&t| t as u64).sum(),
            steps: new
                .steps
                .iter()
                .chain(&new.end_steps)
                .map(|&s| s as u64)
                .sum(),
            ..WorkBound::default()
        };
        for path in 0..paths {
            let records = old.count(path).max(new.count(path));
            bound.records += records as u64;
            // The last flight ends past the last record: one slot more.
            let slots = || (0..=records).map(|k| (k, old.slot(path, k), new.slot(path, k)));
            let mut first_moved = None;
            for (k, a, b) in slots() {
                if a.record == b.record {
                    continue;
                }
                bound.records_changed += 1;
                bound.terms_changed += b.terms as u64;
                if same_place(&a.record, &b.record) {
                    bound.records_power_only += 1;
                } else {
                    bound.terms_moved_old += a.terms as u64;
                    first_moved.get_or_insert(k);
                }
            }
            let Some(first) = first_moved else {
                continue;
            };
            bound.paths_moved += 1;
            for (k, a, b) in slots().skip(first) {
                let steps = b.steps as u64;
                bound.steps_retracked += steps;
                bound.steps_resumed += if k == first {
                    steps.saturating_sub(a.steps as u64)
                } else {
                    steps
                };
            }
        }
        bound
    }

    /// Share of the new full gather's terms that an exact update must form.
    pub fn terms_share(&self) -> f64 {
        self.terms_changed as f64 / self.terms.max(1) as f64
    }

    /// Share of the new full trace's steps that an exact update must track at least.
    pub fn steps_share(&self) -> f64 {
        self.steps_resumed as f64 / self.steps.max(1) as f64
    }

    /// The highest speedup an exact update can have over a full recompute whose trace takes
    /// `trace_share` of its time: the trace's time scaled by `steps_share`, the rest by
    /// `terms_share`, everything else free.
    pub fn speedup_bound(&self, trace_share: f64) -> f64 {
        let trace_share = trace_share.clamp(0.0, 1.0);
        let work = trace_share * self.steps_share() + (1.0 - trace_share) * self.terms_share();
        if work > 0.0 {
            1.0 / work
        } else {
            f64::INFINITY
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(x: f32, power: f32) -> PhotonRecord {
        PhotonRecord {
            position: [x, 0.0, 0.0],
            cell: 1,
            power: [power; 3],
            hist_lo: 0,
            direction: [0.0, 0.0, 1.0],
            hist_hi: 0,
        }
    }

    /// Three paths of two records: one unchanged, one whose second record only changed
    /// power, one whose first record moved (and whose second vanished: its last flight, 1
    /// step, left the volume).
    fn censuses() -> (Census, Census) {
        let old = Census {
            terms: vec![10, 20, 5, 7, 30, 40],
            steps: vec![3, 4, 2, 6, 5, 9],
            records: vec![
                record(0.1, 1.0),
                record(0.2, 0.5),
                record(0.3, 1.0),
                record(0.4, 0.5),
                record(0.5, 1.0),
                record(0.6, 0.5),
            ],
            path_starts: vec![0, 2, 4, 6],
            end_steps: vec![0; 3],
        };
        let mut new = old.clone();
        new.records[3] = record(0.4, 0.25);
        new.terms[3] = 7;
        new.records[4] = record(0.55, 1.0);
        new.terms[4] = 12;
        new.steps[4] = 8;
        new.records.pop();
        new.terms.pop();
        new.steps.pop();
        new.path_starts[3] = 5;
        new.end_steps[2] = 1;
        (old, new)
    }

    #[test]
    fn the_bound_counts_what_changed_records_and_moved_flights_need() {
        let (old, new) = censuses();
        let b = WorkBound::between(&old, &new);
        assert_eq!(b.records, 6);
        assert_eq!(b.records_changed, 3);
        assert_eq!(b.records_power_only, 1);
        assert_eq!(b.paths, 3);
        assert_eq!(b.paths_moved, 1);
        assert_eq!(b.terms, 10 + 20 + 5 + 7 + 12);
        // New versions: the recoloured record's 7 and the moved one's 12 (the vanished one
        // gives none); the old versions of the moved and the vanished: 30 + 40.
        assert_eq!(b.terms_changed, 7 + 12);
        assert_eq!(b.terms_moved_old, 30 + 40);
        assert_eq!(b.steps, 3 + 4 + 2 + 6 + 8 + 1);
        // The moved path's flights from its first moved slot: 8 + 1; resumed past the old
        // flight's 5 steps: 3 + 1.
        assert_eq!(b.steps_retracked, 8 + 1);
        assert_eq!(b.steps_resumed, 3 + 1);
    }

    #[test]
    fn the_speedup_bound_weighs_the_trace_and_the_gather_by_their_time() {
        let (old, new) = censuses();
        let b = WorkBound::between(&old, &new);
        let (steps, terms) = (4.0 / 24.0, 19.0 / 54.0);
        assert!((b.speedup_bound(0.0) - 1.0 / terms).abs() < 1e-12);
        assert!((b.speedup_bound(1.0) - 1.0 / steps).abs() < 1e-12);
        assert!((b.speedup_bound(0.25) - 1.0 / (0.25 * steps + 0.75 * terms)).abs() < 1e-12);
        // An edit that changes nothing costs nothing.
        assert_eq!(
            WorkBound::between(&old, &old).speedup_bound(0.5),
            f64::INFINITY
        );
    }
}
