//! Observed colour: one 8-bit sRGB colour ([`Rgb`], as the camera's RGB8 image gives it) and the
//! running sums a fruit's mean colour is kept in ([`RgbSum`]).
//!
//! Sums of integers rather than a floating mean, so that two copies of a trolley's planner that
//! add the same samples in any order hold the same sums, and a copy made from a snapshot (which
//! carries the sums) goes on exactly as the original does.

use serde::{Deserialize, Serialize};

/// An 8-bit sRGB colour as the camera delivers it (no gamma or white balance applied).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Rgb {
    pub r: u8,
    pub g: u8,
    pub b: u8,
}

impl Rgb {
    pub const fn new(r: u8, g: u8, b: u8) -> Self {
        Self { r, g, b }
    }

    /// `#rrggbb`, lower case (CSV, CSS).
    pub fn hex(&self) -> String {
        format!("#{:02x}{:02x}{:02x}", self.r, self.g, self.b)
    }

    /// Red is the largest channel by `margin` or more over both others.
    pub fn is_red_dominant(&self, margin: u8) -> bool {
        let (r, g, b) = (i32::from(self.r), i32::from(self.g), i32::from(self.b));
        r >= g + i32::from(margin) && r >= b + i32::from(margin)
    }
}

impl From<[u8; 3]> for Rgb {
    fn from([r, g, b]: [u8; 3]) -> Self {
        Self { r, g, b }
    }
}

/// Running sums of colour samples: their red, green and blue totals and how many there were.
/// Saturating: sums read from a hostile snapshot cannot make an addition overflow.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RgbSum {
    pub r: u64,
    pub g: u64,
    pub b: u64,
    pub samples: u64,
}

impl RgbSum {
    /// Adds one sample.
    pub fn add(&mut self, c: Rgb) {
        self.r = self.r.saturating_add(u64::from(c.r));
        self.g = self.g.saturating_add(u64::from(c.g));
        self.b = self.b.saturating_add(u64::from(c.b));
        self.samples = self.samples.saturating_add(1);
    }

    /// Adds another sum's samples.
    pub fn merge(&mut self, other: &RgbSum) {
        self.r = self.r.saturating_add(other.r);
        self.g = self.g.saturating_add(other.g);
        self.b = self.b.saturating_add(other.b);
        self.samples = self.samples.saturating_add(other.samples);
    }

    /// The mean colour, each channel rounded to the nearest integer; `None` without samples.
    /// A channel whose sum exceeds 255 per sample (not from real samples) reads as 255.
    pub fn mean(&self) -> Option<Rgb> {
        let n = self.samples;
        if n == 0 {
            return None;
        }
        let channel =
            |sum: u64| ((u128::from(sum) * 2 + u128::from(n)) / (2 * u128::from(n))).min(255) as u8;
        Some(Rgb::new(channel(self.r), channel(self.g), channel(self.b)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_mean_rounds_and_needs_samples() {
        let mut sum = RgbSum::default();
        assert_eq!(sum.mean(), None);
        sum.add(Rgb::new(200, 10, 0));
        sum.add(Rgb::new(101, 11, 1));
        assert_eq!(sum.mean(), Some(Rgb::new(151, 11, 1)));
        let mut other = RgbSum::default();
        other.add(Rgb::new(0, 0, 2));
        sum.merge(&other);
        assert_eq!(sum.samples, 3);
        assert_eq!(sum.mean(), Some(Rgb::new(100, 7, 1)));
        assert_eq!(Rgb::new(180, 40, 12).hex(), "#b4280c");
        assert!(Rgb::new(180, 40, 12).is_red_dominant(50));
        assert!(!Rgb::new(90, 60, 12).is_red_dominant(50));
    }

    #[test]
    fn hostile_sums_saturate_rather_than_overflow() {
        let mut sum = RgbSum {
            r: u64::MAX,
            g: 0,
            b: u64::MAX - 1,
            samples: 1,
        };
        sum.add(Rgb::new(255, 255, 255));
        sum.merge(&RgbSum {
            r: u64::MAX,
            g: 1,
            b: 1,
            samples: u64::MAX,
        });
        assert_eq!((sum.r, sum.samples), (u64::MAX, u64::MAX));
        assert_eq!(sum.mean().map(|c| c.r), Some(1));
        let broken = RgbSum {
            r: 1000,
            g: 0,
            b: 0,
            samples: 1,
        };
        assert_eq!(broken.mean(), Some(Rgb::new(255, 0, 0)));
    }
}
