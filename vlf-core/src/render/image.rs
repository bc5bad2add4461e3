//! Rendered images: linear radiance in memory, written as PFM, EXR or PNG.
//!
//! A rendering of the light field is a measurement (radiance per pixel), so
//! the lossless formats keep it linear and in full `f32`: PFM because it is
//! trivial, dependency-free and easy to compare bit for bit in tests (it is
//! written and read by hand here), EXR because every HDR viewer opens it.
//! PNG is for looking at: radiance is scaled by `2^exposure`, clamped to
//! `[0, 1]` and encoded with the exact sRGB transfer curve to 8 bits.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use crate::{Error, Result};

/// An RGB image of linear radiance.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    /// Row-major, top row first, `width × height` linear RGB values.
    pub pixels: Vec<[f32; 3]>,
}

/// The formats [`Image::save`] writes, for error messages.
const SUPPORTED: &str = ".pfm (linear float), .exr (linear float), .png (tone-mapped sRGB)";

/// The sRGB opto-electronic transfer function (IEC 61966-2-1), on `[0, 1]`.
pub fn srgb_oetf(linear: f64) -> f64 {
    if linear <= 0.003_130_8 {
        12.92 * linear
    } else {
        1.055 * linear.powf(1.0 / 2.4) - 0.055
    }
}

/// Tone maps one linear value for PNG output: `× 2^exposure`, clamp to
/// `[0, 1]` (NaN → 0), sRGB encode, round to 8 bits.
pub fn tone_map(linear: f32, exposure: f64) -> u8 {
    let v = linear as f64 * exposure.exp2();
    // Written so that NaN becomes 0.
    let v = if v > 0.0 { v.min(1.0) } else { 0.0 };
    (srgb_oetf(v) * 255.0).round() as u8
}

impl Image {
    /// A black image.
    pub fn new(width: u32, height: u32) -> Image {
        Image {
            width,
            height,
            pixels: vec![[0.0; 3]; width as usize * height as usize],
        }
    }

    /// The pixel in column `x`, row `y` (row 0 at the top).
    pub fn get(&self, x: u32, y: u32) -> [f32; 3] {
        self.pixels[y as usize * self.width as usize + x as usize]
    }

    /// Mean of each channel over all pixels (0 for an empty image).
    pub fn mean(&self) -> [f64; 3] {
        let mut sum = [0.0f64; 3];
        for p in &self.pixels {
            for c in 0..3 {
                sum[c] += p[c] as f64;
            }
        }
        let n = self.pixels.len().max(1) as f64;
        sum.map(|s| s / n)
    }

    fn check_size(&self) -> Result<()> {
        if self.pixels.len() as u64 != self.width as u64 * self.height as u64 {
            return Err(Error::Parameter(format!(
                "image of {}x{} pixels holds {} values",
                self.width,
                self.height,
                self.pixels.len()
            )));
        }
        Ok(())
    }

    /// Writes the image, the format chosen by the extension of `path`
    /// (case-insensitive): `.pfm` and `.exr` linear float RGB, `.png`
    /// tone-mapped with [`tone_map`] (`exposure` in stops, ignored by the
    /// float formats but required to be finite).
    pub fn save(&self, path: impl AsRef<Path>, exposure: f64) -> Result<()> {
        let path = path.as_ref();
        let extension = Image::check_output(path, exposure)?;
        self.check_size()?;
        match extension.as_str() {
            "pfm" => self.save_pfm(path),
            "exr" => {
                let data: Vec<f32> = self.pixels.iter().flatten().copied().collect();
                let buffer = ::image::Rgb32FImage::from_raw(self.width, self.height, data)
                    .ok_or_else(|| Error::Parameter("image buffer size mismatch".into()))?;
                buffer
                    .save_with_format(path, ::image::ImageFormat::OpenExr)
                    .map_err(|e| image_error(path, e))
            }
            _ => {
                let data: Vec<u8> = self.pixels.iter().flatten().map(|&v| tone_map(v, exposure)).collect();
                let buffer = ::image::RgbImage::from_raw(self.width, self.height, data)
                    .ok_or_else(|| Error::Parameter("image buffer size mismatch".into()))?;
                buffer
                    .save_with_format(path, ::image::ImageFormat::Png)
                    .map_err(|e| image_error(path, e))
            }
        }
    }

    /// What [`Image::save`] would refuse before it has an image to write: an extension other
    /// than `.pfm`, `.exr` or `.png`, an exposure that is not finite, a folder that does not
    /// exist. A renderer asks first, so a minute's rendering is not lost to a typo. Returns the
    /// extension, lower-case.
    pub fn check_output(path: &Path, exposure: f64) -> Result<String> {
        let extension = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        if !matches!(extension.as_str(), "pfm" | "exr" | "png") {
            return Err(Error::Parameter(format!(
                "cannot write image {}: unsupported extension '{extension}', use one of {SUPPORTED}",
                path.display()
            )));
        }
        if !exposure.is_finite() {
            return Err(Error::Parameter(format!("exposure must be finite, got {exposure}")));
        }
        if let Some(folder) = path.parent().filter(|f| !f.as_os_str().is_empty())
            && !folder.is_dir()
        {
            return Err(Error::Parameter(format!(
                "cannot write image {}: the folder {} does not exist",
                path.display(),
                folder.display()
            )));
        }
        Ok(extension)
    }

    /// Standard PFM: `PF\n{w} {h}\n-1.0\n` (negative scale: little-endian),
    /// then `f32` RGB rows from the bottom row to the top one.
    fn save_pfm(&self, path: &Path) -> Result<()> {
        let file = File::create(path).map_err(|e| Error::io(path, e))?;
        let mut out = BufWriter::new(file);
        let write = |out: &mut BufWriter<File>| -> std::io::Result<()> {
            write!(out, "PF\n{} {}\n-1.0\n", self.width, self.height)?;
            let width = self.width as usize;
            if width > 0 {
                for row in self.pixels.chunks_exact(width).rev() {
                    for v in row.iter().flatten() {
                        out.write_all(&v.to_le_bytes())?;
                    }
                }
            }
            out.flush()
        };
        write(&mut out).map_err(|e| Error::io(path, e))
    }

    /// Reads a PFM file: `PF` (RGB) or `Pf` (grey, expanded to RGB), either
    /// endianness (by the sign of the scale, whose magnitude is ignored).
    /// Malformed or truncated files give [`Error::Format`].
    pub fn load_pfm(path: impl AsRef<Path>) -> Result<Image> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        parse_pfm(&bytes).map_err(|message| Error::Format {
            path: path.to_path_buf(),
            message,
        })
    }
}

fn image_error(path: &Path, e: ::image::ImageError) -> Error {
    match e {
        ::image::ImageError::IoError(io) => Error::io(path, io),
        other => Error::io(path, std::io::Error::other(other.to_string())),
    }
}

/// Reads one whitespace-delimited header token starting at `*pos` (after
/// skipping whitespace). `None` at the end of the data or when the token is
/// implausibly long.
fn header_token<'a>(bytes: &'a [u8], pos: &mut usize) -> Option<&'a [u8]> {
    while *pos < bytes.len() && bytes[*pos].is_ascii_whitespace() {
        *pos += 1;
    }
    let start = *pos;
    while *pos < bytes.len() && !bytes[*pos].is_ascii_whitespace() && *pos - start < 64 {
        *pos += 1;
    }
    (*pos > start).then(|| &bytes[start..*pos])
}

fn show(token: &[u8]) -> String {
    String::from_utf8_lossy(token).chars().take(20).collect()
}

fn parse_pfm(bytes: &[u8]) -> std::result::Result<Image, String> {
    let mut pos = 0;
    let channels = match bytes.get(..2) {
        Some(b"PF") => 3usize,
        Some(b"Pf") => 1,
        _ => {
            let head = &bytes[..bytes.len().min(2)];
            return Err(format!(
                "not a PFM file: starts with '{}', expected 'PF' or 'Pf'",
                show(head)
            ));
        }
    };
    pos += 2;
    if bytes.get(pos).is_none_or(|b| !b.is_ascii_whitespace()) {
        return Err("not a PFM file: no whitespace after the 'PF'/'Pf' magic".into());
    }
    let mut dimension = |name: &str| -> std::result::Result<u32, String> {
        let token = header_token(bytes, &mut pos).ok_or_else(|| format!("truncated header: no {name}"))?;
        let text = std::str::from_utf8(token).ok();
        match text.and_then(|t| t.parse::<u32>().ok()) {
            Some(v) if v > 0 => Ok(v),
            _ => Err(format!("invalid {name} '{}' in the header", show(token))),
        }
    };
    let width = dimension("width")?;
    let height = dimension("height")?;
    let token = header_token(bytes, &mut pos).ok_or("truncated header: no scale")?;
    let scale = std::str::from_utf8(token).ok().and_then(|t| t.parse::<f64>().ok());
    let little_endian = match scale {
        Some(s) if s.is_finite() && s != 0.0 => s < 0.0,
        _ => return Err(format!("invalid scale '{}' in the header", show(token))),
    };
    // Exactly one whitespace byte separates the header from the data.
    if pos >= bytes.len() {
        return Err("truncated header: nothing after the scale".into());
    }
    pos += 1;
    let data = &bytes[pos..];
    // u128: cannot overflow (2^32 × 2^32 × 12).
    let expected = width as u128 * height as u128 * channels as u128 * 4;
    if (data.len() as u128) < expected {
        return Err(format!(
            "truncated pixel data: {width}x{height} with {channels} channel(s) needs {expected} bytes, found {}",
            data.len()
        ));
    }
    if data.len() as u128 > expected {
        return Err(format!(
            "{} unexpected bytes after the pixel data of {width}x{height} with {channels} channel(s)",
            data.len() as u128 - expected
        ));
    }
    let values: Vec<f32> = data
        .chunks_exact(4)
        .map(|b| {
            let b = [b[0], b[1], b[2], b[3]];
            if little_endian {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            }
        })
        .collect();
    let (w, h) = (width as usize, height as usize);
    let mut pixels = Vec::with_capacity(w * h);
    // File rows go bottom to top; ours top to bottom.
    for row in values.chunks_exact(w * channels).rev() {
        if channels == 3 {
            pixels.extend(row.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
        } else {
            pixels.extend(row.iter().map(|&g| [g; 3]));
        }
    }
    debug_assert_eq!(pixels.len(), w * h);
    Ok(Image { width, height, pixels })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scratch directory for one test, removed when dropped (pass or fail).
    fn scratch() -> tempfile::TempDir {
        tempfile::Builder::new()
            .prefix("vlf-render-image-")
            .tempdir()
            .expect("scratch directory")
    }

    /// 3 × 2, top row red, bottom row blue-ish, with awkward floats.
    fn sample() -> Image {
        Image {
            width: 3,
            height: 2,
            pixels: vec![
                [1.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.1, 0.2, 1.0 / 3.0],
                [1e-30, 7.5e10, -0.0],
                [0.0, 0.0, 12.25],
            ],
        }
    }

    fn format_message(result: Result<Image>) -> String {
        match result {
            Err(Error::Format { message, .. }) => message,
            other => panic!("expected a format error, got {other:?}"),
        }
    }

    #[test]
    fn pfm_round_trip_is_bit_exact_and_bottom_up() {
        let dir = scratch();
        let image = sample();
        let path = dir.path().join("roundtrip.PFM");
        image.save(&path, 0.0).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let header = b"PF\n3 2\n-1.0\n";
        assert_eq!(&bytes[..header.len()], header);
        assert_eq!(bytes.len(), header.len() + 3 * 2 * 3 * 4);
        // The first data row is the image's bottom row, little-endian.
        let first = f32::from_le_bytes(bytes[header.len()..header.len() + 4].try_into().unwrap());
        assert_eq!(first, 0.1);
        let last_row = &bytes[header.len() + 3 * 3 * 4..];
        assert_eq!(f32::from_le_bytes(last_row[..4].try_into().unwrap()), 1.0);
        assert_eq!(f32::from_le_bytes(last_row[4..8].try_into().unwrap()), 0.0);
        let back = Image::load_pfm(&path).unwrap();
        assert_eq!(back.width, 3);
        assert_eq!(back.height, 2);
        let bits = |i: &Image| i.pixels.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back), bits(&image));
    }

    #[test]
    fn pfm_big_endian_and_grey() {
        let dir = scratch();
        // Big-endian RGB, 1 × 2: bottom row first in the file.
        let mut bytes = b"PF\n1 2\n1.0\n".to_vec();
        for v in [0.0f32, 0.5, 1.0, 2.0, 3.0, 4.0] {
            bytes.extend_from_slice(&v.to_be_bytes());
        }
        let path = dir.path().join("big.pfm");
        std::fs::write(&path, &bytes).unwrap();
        let image = Image::load_pfm(&path).unwrap();
        assert_eq!(image.pixels, vec![[2.0, 3.0, 4.0], [0.0, 0.5, 1.0]]);
        // Little-endian grey, 2 × 1, header split over other whitespace.
        let mut bytes = b"Pf 2\n1 -2.5\n".to_vec();
        for v in [0.25f32, 8.0] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        std::fs::write(&path, &bytes).unwrap();
        let image = Image::load_pfm(&path).unwrap();
        assert_eq!(image.pixels, vec![[0.25; 3], [8.0; 3]]);
        assert_eq!(image.mean(), [4.125; 3]);
    }

    #[test]
    fn bad_pfm_files_are_format_errors() {
        let dir = scratch();
        let path = dir.path().join("good.pfm");
        sample().save(&path, 0.0).unwrap();
        let good = std::fs::read(&path).unwrap();
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (good[..good.len() - 1].to_vec(), "truncated pixel data"),
            (good[..20].to_vec(), "truncated pixel data"),
            (good[..5].to_vec(), "truncated header: no height"),
            (b"PF\n3 2\n".to_vec(), "truncated header: no scale"),
            (b"PF\n3 2\n-1.0".to_vec(), "truncated header: nothing after the scale"),
            ([good.as_slice(), b"x"].concat(), "1 unexpected bytes"),
            (Vec::new(), "not a PFM file"),
            (b"P6\n3 2\n255\n".to_vec(), "not a PFM file: starts with 'P6'"),
            (b"PFx".to_vec(), "no whitespace"),
            (b"PF\nthree 2\n-1.0\n".to_vec(), "invalid width 'three'"),
            (b"PF\n3 0\n-1.0\n".to_vec(), "invalid height '0'"),
            (b"PF\n3 -2\n-1.0\n".to_vec(), "invalid height '-2'"),
            (b"PF\n99999999999 2\n-1.0\n".to_vec(), "invalid width"),
            (b"PF\n3 2\nnan\n".to_vec(), "invalid scale 'nan'"),
            (b"PF\n3 2\n0\n".to_vec(), "invalid scale '0'"),
            (b"PF\n4294967295 4294967295\n-1\n".to_vec(), "truncated pixel data"),
        ];
        for (bytes, needle) in cases {
            std::fs::write(&path, &bytes).unwrap();
            let message = format_message(Image::load_pfm(&path));
            assert!(message.contains(needle), "'{message}' lacks '{needle}'");
        }
        let missing = Image::load_pfm(dir.path().join("does-not-exist.pfm"));
        assert!(matches!(missing, Err(Error::Io { .. })), "{missing:?}");
    }

    #[test]
    fn png_tone_mapping() {
        let dir = scratch();
        assert_eq!(tone_map(0.5, 0.0), 188);
        assert_eq!(tone_map(0.25, 1.0), 188, "exposure 1 doubles");
        assert_eq!(tone_map(1.0, -1.0), 188);
        assert_eq!(tone_map(0.0, 0.0), 0);
        assert_eq!(tone_map(-3.0, 0.0), 0);
        assert_eq!(tone_map(f32::NAN, 0.0), 0);
        assert_eq!(tone_map(1.0, 0.0), 255);
        assert_eq!(tone_map(7.0, 0.0), 255);
        assert_eq!(tone_map(f32::INFINITY, 0.0), 255);
        // Linear segment: 0.002 × 12.92 × 255 = 6.59 → 7.
        assert_eq!(tone_map(0.002, 0.0), 7);
        // Continuity of the exact curve at the knee.
        assert!((srgb_oetf(0.003_130_8) - (1.055 * 0.003_130_8f64.powf(1.0 / 2.4) - 0.055)).abs() < 1e-6);
        assert!((srgb_oetf(0.5) - 0.735_356_6).abs() < 1e-6);

        let image = Image {
            width: 2,
            height: 1,
            pixels: vec![[0.5, 0.25, 0.0], [1.0, 2.0, 0.125]],
        };
        let path = dir.path().join("tone.Png");
        image.save(&path, 0.0).unwrap();
        let png = ::image::open(&path).unwrap().to_rgb8();
        assert_eq!(png.dimensions(), (2, 1));
        assert_eq!(png.get_pixel(0, 0).0, [188, 137, 0]);
        assert_eq!(png.get_pixel(1, 0).0, [255, 255, 99]);
        image.save(&path, 1.0).unwrap();
        let png = ::image::open(&path).unwrap().to_rgb8();
        assert_eq!(png.get_pixel(0, 0).0, [255, 188, 0]);
        assert_eq!(png.get_pixel(1, 0).0, [255, 255, 137]);
    }

    #[test]
    fn exr_round_trip() {
        let dir = scratch();
        let image = sample();
        let path = dir.path().join("linear.exr");
        image.save(&path, 0.0).unwrap();
        let back = ::image::open(&path).unwrap().to_rgb32f();
        assert_eq!(back.dimensions(), (3, 2));
        for (y, row) in image.pixels.chunks(3).enumerate() {
            for (x, p) in row.iter().enumerate() {
                let q = back.get_pixel(x as u32, y as u32).0;
                for c in 0..3 {
                    let tolerance = 1e-6 * p[c].abs().max(1e-30);
                    assert!((q[c] - p[c]).abs() <= tolerance, "({x}, {y}) {c}: {} vs {}", q[c], p[c]);
                }
            }
        }
    }

    #[test]
    fn unsupported_extensions_and_bad_arguments() {
        let dir = scratch();
        let image = sample();
        for name in ["out.jpg", "out", "out.pfm.txt"] {
            match image.save(dir.path().join(name), 0.0) {
                Err(Error::Parameter(m)) => {
                    assert!(m.contains(".pfm") && m.contains(".exr") && m.contains(".png"), "{m}")
                }
                other => panic!("{name}: {other:?}"),
            }
        }
        assert!(matches!(
            image.save(dir.path().join("x.png"), f64::NAN),
            Err(Error::Parameter(_))
        ));
        let mut broken = sample();
        broken.pixels.pop();
        assert!(matches!(
            broken.save(dir.path().join("x.pfm"), 0.0),
            Err(Error::Parameter(_))
        ));
        // A folder that is not there is named before anything is written (and can be checked
        // before rendering: `check_output`); a file that cannot be written is an I/O error.
        let unwritable = dir.path().join("no-such-dir").join("x.pfm");
        match Image::check_output(&unwritable, 0.0) {
            Err(Error::Parameter(m)) => assert!(m.contains("no-such-dir") && m.contains("does not exist"), "{m}"),
            other => panic!("{other:?}"),
        }
        assert!(matches!(image.save(&unwritable, 0.0), Err(Error::Parameter(_))));
        let a_folder = dir.path().join("folder.pfm");
        std::fs::create_dir(&a_folder).unwrap();
        assert!(matches!(image.save(&a_folder, 0.0), Err(Error::Io { .. })));
        assert_eq!(Image::check_output(Path::new("x.PNG"), 0.0).unwrap(), "png");
    }

    #[test]
    fn mean_and_get() {
        let image = sample();
        assert_eq!(image.get(2, 1), [0.0, 0.0, 12.25]);
        let m = image.mean();
        assert!((m[0] - (3.0 + 0.1f32 as f64 + 1e-30f32 as f64) / 6.0).abs() < 1e-12);
        assert_eq!(Image::new(0, 0).mean(), [0.0; 3]);
        assert_eq!(Image::new(2, 3).pixels.len(), 6);
    }
}
