//! How far an image is from a reference: the error measures of the accuracy
//! study (`vlf study`) and of renderer-against-renderer tests.
//!
//! All measures are **relative to the reference's mean** `μ = mean(ref)`
//! over all pixels and channels, not per pixel: dividing by each pixel's own
//! value would let a few dark pixels (shadows, black mirrors) dominate.
//! With `x` the image, `r` the reference and `P` the pixels (× 3 channels):
//!
//! * **relative RMSE** `√(Σ (x − r)² / |P|) / μ`: everything, noise and
//!   bias, edges included;
//! * **mean error** `(mean(x) − μ) / μ`, signed: lost or invented energy;
//! * **block error**: the relative RMSE of the means of `b × b` pixel blocks
//!   (partial blocks at the right and bottom edges count with their own
//!   pixel count). A field blurs shadow and mirror edges by a sub-pixel
//!   amount that dominates the pixel RMSE yet is invisible at a distance;
//!   block means keep the low-frequency error (wrong brightness, missing
//!   light paths) and average the placement of edges away;
//! * **masked RMSE**: the relative RMSE over the pixels of a mask (e.g. those
//!   showing a mirror), normalised by the reference's mean over the mask.
//!
//! Pixels may be **excluded** from every measure (blocks average the pixels
//! left): a study leaves out the pixels showing an emitter and their
//! neighbours, because emitters are drawn exactly by any renderer and only
//! their sub-pixel coverage differs — yet at tens of times the scene's mean
//! radiance, those few edge pixels would otherwise decide every number.
//!
//! Images must have the same size; a mismatch is an [`Error::Parameter`].

use super::Image;
use crate::{Error, Result};

/// The error of an image against a reference; see the module docs for the
/// formulas. All fields are dimensionless ratios (0.01 = 1 %).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Comparison {
    pub relative_rmse: f64,
    pub mean_error: f64,
    pub block_error: f64,
    /// Block edge (pixels) used for [`Comparison::block_error`].
    pub block: u32,
    /// Relative RMSE over the masked pixels; `None` without a mask or when
    /// it selects no pixel, or when the reference is black there.
    pub masked_rmse: Option<f64>,
}

fn check_same_size(image: &Image, reference: &Image) -> Result<()> {
    if image.width != reference.width || image.height != reference.height {
        return Err(Error::Parameter(format!(
            "cannot compare a {}x{} image with a {}x{} reference",
            image.width, image.height, reference.width, reference.height
        )));
    }
    if image.pixels.len() != reference.pixels.len() || image.pixels.is_empty() {
        return Err(Error::Parameter("cannot compare empty or malformed images".into()));
    }
    Ok(())
}

fn mean_of(pixels: impl Iterator<Item = [f32; 3]>) -> (f64, usize) {
    let (mut sum, mut n) = (0.0, 0usize);
    for p in pixels {
        sum += p.iter().map(|&c| c as f64).sum::<f64>();
        n += 1;
    }
    (if n > 0 { sum / (3 * n) as f64 } else { 0.0 }, n)
}

/// Which pixels count (see the module docs). Masks are row-major like the
/// images, `true` = selected.
#[derive(Clone, Copy, Debug, Default)]
pub struct Pixels<'a> {
    /// Pixels left out of every measure.
    pub exclude: Option<&'a [bool]>,
    /// Pixels of the masked RMSE (among those not excluded).
    pub mask: Option<&'a [bool]>,
}

/// Compares `image` with `reference` (same size): every measure of the
/// module docs, with blocks of `block × block` pixels, over the pixels
/// `pixels` selects.
pub fn compare(image: &Image, reference: &Image, block: u32, pixels: Pixels) -> Result<Comparison> {
    check_same_size(image, reference)?;
    if block == 0 {
        return Err(Error::Parameter("block size must be at least 1 pixel".into()));
    }
    for (name, m) in [("mask", pixels.mask), ("exclusion mask", pixels.exclude)] {
        if let Some(m) = m
            && m.len() != reference.pixels.len()
        {
            return Err(Error::Parameter(format!(
                "{name} of {} pixels for an image of {}",
                m.len(),
                reference.pixels.len()
            )));
        }
    }
    let keep: Vec<bool> = match pixels.exclude {
        Some(e) => e.iter().map(|&x| !x).collect(),
        None => vec![true; reference.pixels.len()],
    };
    let kept = |img: &Image| -> Vec<[f32; 3]> {
        img.pixels
            .iter()
            .zip(&keep)
            .filter(|(_, k)| **k)
            .map(|(p, _)| *p)
            .collect()
    };
    let (x_kept, r_kept) = (kept(image), kept(reference));
    if r_kept.is_empty() {
        return Err(Error::Parameter("every pixel is excluded: nothing to compare".into()));
    }
    let mask = pixels.mask.map(|m| {
        m.iter()
            .zip(&keep)
            .filter(|(_, k)| **k)
            .map(|(m, _)| *m)
            .collect::<Vec<bool>>()
    });
    let mask = mask.as_deref();
    let (mu, _) = mean_of(r_kept.iter().copied());
    if !(mu.is_finite() && mu > 0.0) {
        return Err(Error::Parameter(format!(
            "the reference's mean must be positive and finite to measure relative errors, got {mu}"
        )));
    }
    let (mean, _) = mean_of(x_kept.iter().copied());
    let squared = |a: &[f32; 3], b: &[f32; 3]| -> f64 { (0..3).map(|c| (a[c] as f64 - b[c] as f64).powi(2)).sum() };
    let sum_sq: f64 = x_kept.iter().zip(&r_kept).map(|(a, b)| squared(a, b)).sum();
    let relative_rmse = (sum_sq / (3 * r_kept.len()) as f64).sqrt() / mu;

    // Block means.
    let (w, h) = (image.width as usize, image.height as usize);
    let b = block as usize;
    let (bw, bh) = (w.div_ceil(b), h.div_ceil(b));
    let mut blocks = vec![([0.0f64; 3], [0.0f64; 3], 0usize); bw * bh];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if !keep[i] {
                continue;
            }
            let entry = &mut blocks[(y / b) * bw + x / b];
            for c in 0..3 {
                entry.0[c] += image.pixels[i][c] as f64;
                entry.1[c] += reference.pixels[i][c] as f64;
            }
            entry.2 += 1;
        }
    }
    blocks.retain(|b| b.2 > 0);
    let block_sq: f64 = blocks
        .iter()
        .map(|(x, r, n)| (0..3).map(|c| ((x[c] - r[c]) / *n as f64).powi(2)).sum::<f64>())
        .sum();
    let block_error = (block_sq / (3 * blocks.len()) as f64).sqrt() / mu;

    let masked_rmse = mask.and_then(|m| {
        let pairs = || {
            x_kept
                .iter()
                .zip(&r_kept)
                .zip(m)
                .filter(|(_, keep)| **keep)
                .map(|(p, _)| p)
        };
        let (mu_mask, n) = mean_of(pairs().map(|(_, r)| *r));
        if n == 0 || mu_mask <= 0.0 {
            return None;
        }
        let sq: f64 = pairs().map(|(a, r)| squared(a, r)).sum();
        Some((sq / (3 * n) as f64).sqrt() / mu_mask)
    });
    Ok(Comparison {
        relative_rmse,
        mean_error: (mean - mu) / mu,
        block_error,
        block,
        masked_rmse,
    })
}

/// Per-pixel error map: `|x − r|` averaged over the channels, divided by the
/// reference's mean (so 0.1 means an error of 10 % of the average
/// brightness), as a single-channel image repeated in RGB.
pub fn error_map(image: &Image, reference: &Image) -> Result<Image> {
    check_same_size(image, reference)?;
    let (mu, _) = mean_of(reference.pixels.iter().copied());
    let mu = if mu > 0.0 { mu } else { 1.0 };
    let pixels = image
        .pixels
        .iter()
        .zip(&reference.pixels)
        .map(|(a, r)| {
            let e = (0..3).map(|c| (a[c] as f64 - r[c] as f64).abs()).sum::<f64>() / 3.0 / mu;
            [e as f32; 3]
        })
        .collect();
    Ok(Image {
        width: image.width,
        height: image.height,
        pixels,
    })
}

/// A false-colour rendering of an [`error_map`] for looking at: 0 is black,
/// `full_scale` and above is white, through blue, magenta and yellow
/// (perceptually ordered, readable in grey). Returns 8-bit RGB rows.
pub fn false_colour(map: &Image, full_scale: f64) -> Vec<u8> {
    const STOPS: [[f64; 3]; 5] = [
        [0.0, 0.0, 0.0],
        [0.1, 0.1, 0.6],
        [0.75, 0.1, 0.55],
        [1.0, 0.8, 0.1],
        [1.0, 1.0, 1.0],
    ];
    let scale = if full_scale > 0.0 { full_scale } else { 1.0 };
    map.pixels
        .iter()
        .flat_map(|p| {
            let t = (p[0] as f64 / scale).clamp(0.0, 1.0) * (STOPS.len() - 1) as f64;
            let i = (t.floor() as usize).min(STOPS.len() - 2);
            let f = t - i as f64;
            let c: [u8; 3] =
                std::array::from_fn(|k| ((STOPS[i][k] * (1.0 - f) + STOPS[i + 1][k] * f) * 255.0).round() as u8);
            c
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(width: u32, height: u32, f: impl Fn(u32, u32) -> [f32; 3]) -> Image {
        let mut img = Image::new(width, height);
        for y in 0..height {
            for x in 0..width {
                img.pixels[(y * width + x) as usize] = f(x, y);
            }
        }
        img
    }

    #[test]
    fn identical_images_have_no_error() {
        let r = image(7, 5, |x, y| [x as f32 + 1.0, y as f32, 0.5]);
        let c = compare(
            &r,
            &r,
            2,
            Pixels {
                exclude: None,
                mask: Some(&[true; 35]),
            },
        )
        .unwrap();
        assert_eq!(c.relative_rmse, 0.0);
        assert_eq!(c.mean_error, 0.0);
        assert_eq!(c.block_error, 0.0);
        assert_eq!(c.masked_rmse, Some(0.0));
    }

    #[test]
    fn uniform_scaling_gives_the_scale_as_every_error() {
        // x = 1.1 r with r constant: every pixel is off by 10 % of the mean.
        let r = image(8, 8, |_, _| [2.0; 3]);
        let x = image(8, 8, |_, _| [2.2; 3]);
        let c = compare(&x, &r, 4, Pixels::default()).unwrap();
        assert!((c.relative_rmse - 0.1).abs() < 1e-6, "{c:?}");
        assert!((c.mean_error - 0.1).abs() < 1e-6);
        assert!((c.block_error - 0.1).abs() < 1e-6);
        assert_eq!(c.masked_rmse, None);
    }

    #[test]
    fn zero_mean_noise_shows_in_pixels_but_not_in_block_means() {
        // A checkerboard of ±0.5 on a mean of 1: pixel RMSE 0.5, mean error 0,
        // and 2×2 blocks average it away exactly.
        let r = image(8, 6, |_, _| [1.0; 3]);
        let x = image(8, 6, |x, y| [if (x + y) % 2 == 0 { 1.5 } else { 0.5 }; 3]);
        let c = compare(&x, &r, 2, Pixels::default()).unwrap();
        assert!((c.relative_rmse - 0.5).abs() < 1e-9);
        assert!(c.mean_error.abs() < 1e-12);
        assert!(c.block_error.abs() < 1e-12);
    }

    #[test]
    fn a_shifted_edge_costs_pixels_but_few_blocks() {
        // A vertical edge moved by one pixel: 1 column of 16 wrong by 1.
        let r = image(16, 16, |x, _| [if x < 8 { 0.0 } else { 2.0 }; 3]);
        let x = image(16, 16, |x, _| [if x < 9 { 0.0 } else { 2.0 }; 3]);
        let c = compare(&x, &r, 16, Pixels::default()).unwrap();
        // mean 1; pixel RMSE = sqrt(16·4 / 256) = 0.5; one 16×16 block off by 2/16.
        assert!((c.relative_rmse - 0.5).abs() < 1e-9, "{c:?}");
        assert!((c.mean_error + 0.125).abs() < 1e-9);
        assert!((c.block_error - 0.125).abs() < 1e-9);
    }

    #[test]
    fn partial_blocks_average_their_own_pixels() {
        // 3 wide with blocks of 2: the right block has one column.
        let r = image(3, 1, |_, _| [1.0; 3]);
        let x = image(3, 1, |x, _| [if x == 2 { 2.0 } else { 1.0 }; 3]);
        let c = compare(&x, &r, 2, Pixels::default()).unwrap();
        // Blocks: [1,1] exact, [2] off by 1 → RMSE over 2 blocks = sqrt(1/2).
        assert!((c.block_error - 0.5f64.sqrt()).abs() < 1e-9, "{c:?}");
    }

    #[test]
    fn the_mask_selects_pixels_and_its_own_normalisation() {
        let r = image(4, 1, |x, _| [if x < 2 { 1.0 } else { 4.0 }; 3]);
        let x = image(4, 1, |x, _| [if x < 2 { 1.0 } else { 5.0 }; 3]);
        let mask = [false, false, true, true];
        let c = compare(
            &x,
            &r,
            1,
            Pixels {
                exclude: None,
                mask: Some(&mask),
            },
        )
        .unwrap();
        // Over the mask: error 1 on a mean of 4.
        assert!((c.masked_rmse.unwrap() - 0.25).abs() < 1e-9);
        let none = compare(
            &x,
            &r,
            1,
            Pixels {
                exclude: None,
                mask: Some(&[false; 4]),
            },
        )
        .unwrap();
        assert_eq!(none.masked_rmse, None);
    }

    #[test]
    fn mismatched_or_black_references_are_errors() {
        let a = image(2, 2, |_, _| [1.0; 3]);
        let b = image(2, 3, |_, _| [1.0; 3]);
        assert!(
            compare(&a, &b, 1, Pixels::default())
                .unwrap_err()
                .to_string()
                .contains("2x2")
        );
        let black = image(2, 2, |_, _| [0.0; 3]);
        assert!(compare(&a, &black, 1, Pixels::default()).is_err());
        assert!(compare(&a, &a, 0, Pixels::default()).is_err());
        assert!(
            compare(
                &a,
                &a,
                1,
                Pixels {
                    exclude: None,
                    mask: Some(&[true])
                }
            )
            .is_err()
        );
    }

    #[test]
    fn excluded_pixels_count_nowhere() {
        // A bright pixel (an emitter's edge) wrong by 100 dominates until excluded.
        let r = image(4, 4, |x, y| [if (x, y) == (0, 0) { 100.0 } else { 1.0 }; 3]);
        let x = image(4, 4, |x, y| [if (x, y) == (0, 0) { 0.0 } else { 1.1 }; 3]);
        let all = compare(&x, &r, 2, Pixels::default()).unwrap();
        assert!(all.relative_rmse > 1.0, "{all:?}");
        let mut exclude = [false; 16];
        exclude[0] = true;
        let c = compare(
            &x,
            &r,
            2,
            Pixels {
                exclude: Some(&exclude),
                mask: None,
            },
        )
        .unwrap();
        assert!((c.relative_rmse - 0.1).abs() < 1e-6, "{c:?}");
        assert!((c.mean_error - 0.1).abs() < 1e-6);
        assert!((c.block_error - 0.1).abs() < 1e-6);
        assert!(
            compare(
                &x,
                &r,
                2,
                Pixels {
                    exclude: Some(&[true; 16]),
                    mask: None
                }
            )
            .is_err()
        );
    }

    #[test]
    fn error_map_is_per_pixel_relative_and_false_colour_spans_the_scale() {
        let r = image(2, 1, |_, _| [2.0; 3]);
        let x = image(2, 1, |x, _| [if x == 0 { 2.0 } else { 3.0 }; 3]);
        let map = error_map(&x, &r).unwrap();
        assert_eq!(map.pixels, vec![[0.0; 3], [0.5; 3]]);
        let rgb = false_colour(&map, 0.5);
        assert_eq!(&rgb[..3], &[0, 0, 0]);
        assert_eq!(&rgb[3..], &[255, 255, 255]);
    }
}
