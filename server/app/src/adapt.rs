//! Per-viewer stream adaptation: while frames keep coming (the picture changes), pick the JPEG
//! quality that lets this viewer take frames at `TARGET_FPS`. The signal is how long the
//! viewer took to take a frame: from sending to its `ack` when the client acknowledges, else
//! how long the socket write blocked. Slow → one step down the ladder at once; fast for a
//! while → one step back up. Qualities come from a short fixed ladder so viewers on similar
//! links share encodings.

use std::time::Duration;

/// Frame rate the adaptation tries to hold for each viewer.
pub const TARGET_FPS: f64 = 15.0;

/// Qualities below the viewer's own choice, best first.
const LADDER: [u8; 4] = [70, 55, 40, 25];

/// Fast deliveries in a row before stepping back up.
const STEP_UP_AFTER: u32 = 8;

#[derive(Debug, Default, Clone)]
pub struct QualityController {
    /// 0: the viewer's own quality; k: `LADDER[k - 1]`.
    level: usize,
    fast_streak: u32,
}

impl QualityController {
    /// The JPEG quality to use now, never above the viewer's `max`.
    pub fn quality(&self, max: u8) -> u8 {
        match self.level {
            0 => max,
            k => LADDER[k - 1].min(max),
        }
    }

    /// Records how long the viewer took to take one frame.
    pub fn observe(&mut self, delivery: Duration) {
        let interval = Duration::from_secs_f64(1.0 / TARGET_FPS);
        if delivery > interval {
            self.level = (self.level + 1).min(LADDER.len());
            self.fast_streak = 0;
        } else if delivery < interval / 3 {
            self.fast_streak += 1;
            if self.fast_streak >= STEP_UP_AFTER && self.level > 0 {
                self.level -= 1;
                self.fast_streak = 0;
            }
        } else {
            self.fast_streak = 0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slow_viewers_get_lower_quality_and_recover() {
        let mut c = QualityController::default();
        assert_eq!(c.quality(85), 85);
        for expected in [70, 55, 40, 25, 25] {
            c.observe(Duration::from_millis(200));
            assert_eq!(c.quality(85), expected);
        }
        // A few fast frames are not enough; a steady fast link climbs back one step at a time.
        for _ in 0..STEP_UP_AFTER - 1 {
            c.observe(Duration::from_millis(5));
        }
        assert_eq!(c.quality(85), 25);
        c.observe(Duration::from_millis(5));
        assert_eq!(c.quality(85), 40);
        for _ in 0..3 * STEP_UP_AFTER {
            c.observe(Duration::from_millis(5));
        }
        assert_eq!(c.quality(85), 85);
    }

    #[test]
    fn middling_deliveries_hold_and_the_viewer_cap_wins() {
        let mut c = QualityController::default();
        c.observe(Duration::from_millis(100));
        for _ in 0..50 {
            c.observe(Duration::from_millis(40));
        }
        assert_eq!(c.quality(85), 70);
        assert_eq!(c.quality(50), 50);
    }
}
