//! glTF materials (metallic-roughness PBR) as VLF materials: ideal diffuse,
//! ideal mirror, isotropic emission.
//!
//! * `baseColorFactor` (linear RGB; alpha ignored) is the reflectance. A
//!   diffuser's `baseColorTexture` multiplies it where the surface's
//!   `TEXCOORD_n` place it: the image (sRGB, decoded to linear) becomes a
//!   scene [`Texture`], averaged over each texel of the field
//!   ([`crate::maps::albedo`]). A mirror's is averaged over the image (a
//!   mirror has one reflectance), with a warning.
//! * **Smooth** (`roughnessFactor` ≤ [`MIRROR_ROUGHNESS`]): glTF's BRDF is a
//!   linear mix of a dielectric and a metal by `metallicFactor` m, so the
//!   metal share becomes an ideal mirror, ρs = m × base, and the rest is
//!   diffuse, ρd = (1 − m) × base. Metallic 1 is a pure mirror (ρs = base);
//!   metallic 0 a pure diffuser (the dielectric's few-percent Fresnel
//!   reflection is neglected, as for any diffuse material here).
//! * **Rough** (roughness above that): the glossy lobe has no counterpart
//!   among ideal diffuse and ideal mirror; the diffuser keeps its albedo:
//!   ρd = base whatever the metallic factor, and a metallic one gets a
//!   warning (its reflection is spread over the hemisphere, not glossy).
//! * `emissiveFactor` × `KHR_materials_emissive_strength` (× the
//!   `emissiveTexture`'s average linear colour, with a warning) is the
//!   emitted radiance `Le`, in the same units as an OBJ's `Ke`.
//! * `doubleSided` is returned to the mesh reader, which emits each triangle
//!   twice, once per side (so both sides reflect, and emit).
//! * Everything else (`metallicRoughnessTexture`, normal and occlusion maps,
//!   `alphaMode`, extensions such as transmission, volume, clearcoat or
//!   sheen) is ignored with a warning naming the material.
//! * Values glTF does not allow (a colour above 1 or below 0) are clamped
//!   into range with a warning, so the result always passes the shared
//!   material checks.

use std::collections::HashMap;
use std::path::Path;

use ::gltf::json;
use json::validation::Checked;

use super::data::{Buffers, image_bytes};
use crate::Error;
use crate::scene::build::{Warnings, fmt_rgb};
use crate::scene::texture::MAX_TEXTURE_SIZE;
use crate::scene::{Material, Rgb, Texture, Wrap};

/// Largest roughness read as an ideal mirror: below it a glossy reflection
/// is sharp to a few degrees (the GGX lobe's width is of order roughness²).
/// An f32, as glTF's factors are: a file's `0.05` is exactly this.
pub(super) const MIRROR_ROUGHNESS: f32 = 0.05;

/// A converted material and whether its triangles are double-sided.
pub(super) struct Converted {
    pub material: Material,
    pub double_sided: bool,
    /// The `TEXCOORD_n` set its albedo texture reads (with `material.albedo_texture`).
    pub tex_coord: u32,
}

/// Converts materials, caching texture averages by image and albedo textures by texture.
pub(super) struct Materials<'a> {
    pub root: &'a json::Root,
    pub dir: &'a Path,
    pub averages: HashMap<usize, Rgb>,
    /// The scene's albedo textures, and which glTF texture each came from.
    pub textures: Vec<Texture>,
    pub texture_of: HashMap<usize, u32>,
}

impl Materials<'_> {
    /// glTF's default material (for a primitive without one): base colour 1,
    /// metallic 1, roughness 1, which the rules above make a white diffuser.
    pub fn default_material() -> Converted {
        Converted {
            material: Material {
                name: "glTF default material".to_string(),
                diffuse: [1.0; 3],
                specular: [0.0; 3],
                emission: [0.0; 3],
                albedo_texture: None,
            },
            double_sided: false,
            tex_coord: 0,
        }
    }

    /// Converts material `index`, adding its warnings.
    pub fn convert(
        &mut self,
        buffers: &mut Buffers,
        index: usize,
        warnings: &mut Warnings,
    ) -> Result<Converted, Error> {
        let file = buffers.file().to_string();
        let Some(m) = self.root.materials.get(index) else {
            return Err(Error::scene(
                &file,
                None,
                format!(
                    "material {index} does not exist (the file has {})",
                    self.root.materials.len()
                ),
            ));
        };
        let name = match &m.name {
            Some(n) if !n.is_empty() => n.clone(),
            _ => format!("material #{index}"),
        };
        let label = format!("material '{name}' (#{index})");
        let fail = |msg: String| Error::scene(&file, None, format!("{label}: {msg}"));
        let mut warn = |msg: String| warnings.push(format!("{file}: {label}: {msg}"));
        let pbr = &m.pbr_metallic_roughness;

        let factor = pbr.base_color_factor.0;
        let mut base = clamp_unit(
            [factor[0], factor[1], factor[2]].map(f64::from),
            "baseColorFactor",
            &mut warn,
        )
        .map_err(fail)?;
        let metallic = clamp_scalar(pbr.metallic_factor.0, "metallicFactor", &mut warn).map_err(fail)?;
        let roughness = clamp_scalar(pbr.roughness_factor.0, "roughnessFactor", &mut warn).map_err(fail)?;
        if pbr.metallic_roughness_texture.is_some() {
            warn("metallicRoughnessTexture ignored: the factors are used".to_string());
        }
        // For messages, as the file writes them.
        let (m_f32, r_f32) = (pbr.metallic_factor.0, pbr.roughness_factor.0);
        let mirror = roughness <= f64::from(MIRROR_ROUGHNESS) && metallic > 0.0;
        // A diffuser's base colour texture is its albedo, sampled per texel of the field; a
        // mirror has one reflectance, so there it is averaged.
        let (mut albedo_texture, mut tex_coord) = (None, 0);
        if let Some(info) = &pbr.base_color_texture {
            if mirror {
                let average = self
                    .texture_average(buffers, info.index.value())
                    .map_err(|m| fail(format!("baseColorTexture: {m}")))?;
                base = mul(base, average);
                warn(format!(
                    "baseColorTexture averaged to {} (linear) over the mirror: a mirror has one reflectance",
                    fmt_rgb(average)
                ));
            } else {
                albedo_texture = Some(
                    self.albedo_texture(buffers, info.index.value())
                        .map_err(|m| fail(format!("baseColorTexture: {m}")))?,
                );
                tex_coord = info.tex_coord;
            }
        }
        let (diffuse, specular) = if roughness <= f64::from(MIRROR_ROUGHNESS) {
            if metallic > 0.0 && metallic < 1.0 {
                warn(format!(
                    "metallic {m_f32} (roughness {r_f32}) read as a partial mirror: \
                     ρs = metallic × base colour, ρd = (1 − metallic) × base colour"
                ));
            }
            (base.map(|b| b * (1.0 - metallic)), base.map(|b| b * metallic))
        } else {
            if metallic > 0.0 {
                warn(format!(
                    "metallic {m_f32} with roughness {r_f32} > {MIRROR_ROUGHNESS}: a rough metal's glossy \
                     reflection is approximated as diffuse, ρd = base colour {} (its albedo); only \
                     roughness ≤ {MIRROR_ROUGHNESS} is an ideal mirror",
                    fmt_rgb(base)
                ));
            }
            (base, [0.0; 3])
        };

        let factor = m.emissive_factor.0.map(f64::from);
        let strength = m
            .extensions
            .as_ref()
            .and_then(|e| e.emissive_strength.as_ref())
            .map_or(1.0, |s| f64::from(s.emissive_strength.0));
        if !(strength.is_finite() && strength >= 0.0) {
            return Err(fail(format!(
                "KHR_materials_emissive_strength {strength} is not a finite number ≥ 0"
            )));
        }
        let mut emission = clamp_emission(factor.map(|f| f * strength), &mut warn).map_err(fail)?;
        if let Some(info) = &m.emissive_texture
            && emission.iter().any(|&e| e > 0.0)
        {
            let average = self
                .texture_average(buffers, info.index.value())
                .map_err(|m| fail(format!("emissiveTexture: {m}")))?;
            emission = mul(emission, average);
            warn(format!(
                "emissiveTexture averaged to {} (linear) over the material: per-texel emission is not supported yet",
                fmt_rgb(average)
            ));
        }

        if m.normal_texture.is_some() || m.occlusion_texture.is_some() {
            warn("normal and occlusion textures ignored".to_string());
        }
        match m.alpha_mode {
            Checked::Valid(json::material::AlphaMode::Opaque) => {}
            _ => warn("alphaMode ignored: the surface is opaque".to_string()),
        }
        if let Some(ext) = &m.extensions {
            for key in ext.others.keys() {
                warn(format!(
                    "extension {key} ignored: only base colour, metallic-roughness and emission are read"
                ));
            }
        }
        Ok(Converted {
            material: Material {
                name,
                diffuse,
                specular,
                emission,
                albedo_texture,
            },
            double_sided: m.double_sided,
            tex_coord,
        })
    }

    /// The scene's albedo texture made from glTF texture `index` (converted once): its image
    /// decoded to linear RGB, box-filtered down to at most [`MAX_TEXTURE_SIZE`] per side, with
    /// its sampler's wrap modes.
    fn albedo_texture(&mut self, buffers: &mut Buffers, index: usize) -> Result<u32, String> {
        if let Some(&known) = self.texture_of.get(&index) {
            return Ok(known);
        }
        let Some(texture) = self.root.textures.get(index) else {
            return Err(format!(
                "texture {index} does not exist (the file has {})",
                self.root.textures.len()
            ));
        };
        let image = texture.source.value();
        let wrap = match texture.sampler {
            None => [Wrap::Repeat; 2],
            Some(s) => {
                let Some(sampler) = self.root.samplers.get(s.value()) else {
                    return Err(format!(
                        "sampler {} does not exist (the file has {})",
                        s.value(),
                        self.root.samplers.len()
                    ));
                };
                let mode = |m: &Checked<json::texture::WrappingMode>| match m {
                    Checked::Valid(json::texture::WrappingMode::ClampToEdge) => Wrap::Clamp,
                    Checked::Valid(json::texture::WrappingMode::MirroredRepeat) => Wrap::Mirror,
                    _ => Wrap::Repeat,
                };
                [mode(&sampler.wrap_s), mode(&sampler.wrap_t)]
            }
        };
        let bytes = image_bytes(self.root, buffers, self.dir, image)?;
        let decoded = decode_image(&bytes, image)?;
        let (width, height, texels) = linear_texture(&decoded).ok_or_else(|| format!("image {image} has no pixels"))?;
        let name = match &self.root.images.get(image).and_then(|i| i.name.clone()) {
            Some(n) => format!("image '{n}' (#{image})"),
            None => format!("image #{image}"),
        };
        self.textures.push(Texture {
            name,
            width,
            height,
            texels,
            wrap,
        });
        let id = self.textures.len() as u32 - 1;
        self.texture_of.insert(index, id);
        Ok(id)
    }

    /// Average linear colour of texture `index`'s image (cached).
    fn texture_average(&mut self, buffers: &mut Buffers, index: usize) -> Result<Rgb, String> {
        let Some(texture) = self.root.textures.get(index) else {
            return Err(format!(
                "texture {index} does not exist (the file has {})",
                self.root.textures.len()
            ));
        };
        let image = texture.source.value();
        if let Some(&average) = self.averages.get(&image) {
            return Ok(average);
        }
        let bytes = image_bytes(self.root, buffers, self.dir, image)?;
        let decoded = decode_image(&bytes, image)?;
        let average = average_linear(&decoded).ok_or_else(|| format!("image {image} has no pixels"))?;
        self.averages.insert(image, average);
        Ok(average)
    }
}

/// What decoding one image may allocate: 512 MiB, an 8K image of four 16-bit channels (and
/// the `image` crate's default, said here because the importer relies on it). An image that
/// decodes to more is refused with its size before its pixels are allocated: a PNG of a few
/// kilobytes may claim 23 000 × 23 000 pixels. Past decoding, the importer holds a piece of a row
/// at a time ([`linear_texture`]), never the whole image again.
const MAX_IMAGE_BYTES: u64 = 512 << 20;

/// Image `image` of the file, decoded from its `bytes` within [`MAX_IMAGE_BYTES`].
fn decode_image(bytes: &[u8], image: usize) -> Result<image::DynamicImage, String> {
    let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| format!("image {image} cannot be read: {e}"))?;
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_IMAGE_BYTES);
    reader.limits(limits);
    reader.decode().map_err(|e| match e {
        image::ImageError::Limits(_) => {
            format!("image {image} decodes to more than {} MiB: {e}", MAX_IMAGE_BYTES >> 20)
        }
        e => format!("image {image} cannot be decoded: {e}"),
    })
}

/// The sRGB transfer function's inverse: an encoded value in `[0, 1]` to
/// linear.
pub(super) fn srgb_to_linear(c: f64) -> f64 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// The pixels of an image are converted in pieces of at most this many of one row: a piece's
/// copy and conversion (12 bytes a pixel) stay small however wide or tall the image is.
const PIECE: u32 = 4096;

/// The image's pieces of rows, in row-major order: `(x, y, piece)`, the piece one row high and
/// at most [`PIECE`] wide, starting at pixel `(x, y)`.
fn pieces(image: &image::DynamicImage) -> impl Iterator<Item = (u32, u32, image::DynamicImage)> + '_ {
    let width = image.width();
    (0..image.height()).flat_map(move |y| {
        (0..width)
            .step_by(PIECE as usize)
            .map(move |x| (x, y, image.crop_imm(x, y, PIECE.min(width - x), 1)))
    })
}

/// Each 8-bit sRGB value, linear: found once, not once per piece of a row.
static SRGB8_LINEAR: std::sync::LazyLock<[f32; 256]> =
    std::sync::LazyLock::new(|| std::array::from_fn(|v| srgb_to_linear(v as f64 / 255.0) as f32));

/// The pixels of `piece` (a crop keeps its image's colour type) as linear RGB, sRGB decoded
/// (alpha ignored), row by row from the top.
fn linear_pixels(piece: &image::DynamicImage) -> Vec<[f32; 3]> {
    match piece.color() {
        image::ColorType::L8 | image::ColorType::La8 | image::ColorType::Rgb8 | image::ColorType::Rgba8 => {
            let lut = &*SRGB8_LINEAR;
            piece.to_rgb8().pixels().map(|p| p.0.map(|v| lut[v as usize])).collect()
        }
        _ => (piece.to_rgb32f().pixels())
            .map(|p| p.0.map(|v| srgb_to_linear(f64::from(v).clamp(0.0, 1.0)) as f32))
            .collect(),
    }
}

/// An sRGB-encoded image as a linear texture of at most [`MAX_TEXTURE_SIZE`] a side: box-filtered
/// down by the smallest whole factor `k` that brings both sides there (a field texel covers far
/// more than a texel of a larger image), each output texel the mean of its `k × k` block (fewer at
/// the edges), its pixels added row by row, left to right. Converted a piece of a row at a time
/// ([`pieces`]), so a large image is never held twice, let alone at 12 bytes a pixel. `None` if it
/// has no pixels.
fn linear_texture(image: &image::DynamicImage) -> Option<(u32, u32, Vec<[f32; 3]>)> {
    let (width, height) = (image.width(), image.height());
    if width == 0 || height == 0 {
        return None;
    }
    let k = width.max(height).div_ceil(MAX_TEXTURE_SIZE);
    if k <= 1 {
        // At most 1024 × 1024 pixels: converted whole.
        return Some((width, height, linear_pixels(image)));
    }
    let (w, h) = (width.div_ceil(k), height.div_ceil(k));
    // Per output texel, the sum of its block's pixels so far and their count.
    let mut sums = vec![([0.0f64; 3], 0u32); (w * h) as usize];
    for (x0, y, piece) in pieces(image) {
        let row = (y / k) * w;
        for (sx, c) in (x0..).zip(linear_pixels(&piece)) {
            let (sum, n) = &mut sums[(row + sx / k) as usize];
            for i in 0..3 {
                sum[i] += c[i] as f64;
            }
            *n += 1;
        }
    }
    let out = (sums.into_iter())
        .map(|(sum, n)| sum.map(|v| (v / n as f64) as f32))
        .collect();
    Some((w, h, out))
}

/// Mean linear RGB of an sRGB-encoded image (alpha ignored); `None` if it
/// has no pixels.
pub(super) fn average_linear(image: &image::DynamicImage) -> Option<Rgb> {
    let pixels = u64::from(image.width()) * u64::from(image.height());
    if pixels == 0 {
        return None;
    }
    let mut sum = [0.0f64; 3];
    let eight_bit = matches!(
        image.color(),
        image::ColorType::L8 | image::ColorType::La8 | image::ColorType::Rgb8 | image::ColorType::Rgba8
    );
    let lut: Vec<f64> = (0..256).map(|v| srgb_to_linear(v as f64 / 255.0)).collect();
    // A piece of a row at a time, in row-major order (the same sums as over the whole image at
    // once), so a large image is never held converted whole.
    for (_, _, piece) in pieces(image) {
        if eight_bit {
            for p in piece.to_rgb8().pixels() {
                for (s, &v) in sum.iter_mut().zip(&p.0) {
                    *s += lut[v as usize];
                }
            }
        } else {
            for p in piece.to_rgb32f().pixels() {
                for (s, &v) in sum.iter_mut().zip(&p.0) {
                    *s += srgb_to_linear(f64::from(v).clamp(0.0, 1.0));
                }
            }
        }
    }
    Some(sum.map(|s| s / pixels as f64))
}

fn mul(a: Rgb, b: Rgb) -> Rgb {
    [a[0] * b[0], a[1] * b[1], a[2] * b[2]]
}

/// A reflectance clamped into `[0, 1]`, warning if it was outside.
fn clamp_unit(c: Rgb, what: &str, warn: &mut impl FnMut(String)) -> Result<Rgb, String> {
    if c.iter().any(|x| !x.is_finite()) {
        return Err(format!("{what} {} is not finite", fmt_rgb(c)));
    }
    let clamped = c.map(|x| x.clamp(0.0, 1.0));
    if clamped != c {
        warn(format!(
            "{what} {} clamped to {} (glTF allows [0, 1])",
            fmt_rgb(c),
            fmt_rgb(clamped)
        ));
    }
    Ok(clamped)
}

/// A factor clamped into `[0, 1]`, warning if it was outside.
fn clamp_scalar(x: f32, what: &str, warn: &mut impl FnMut(String)) -> Result<f64, String> {
    let x = f64::from(x);
    if !x.is_finite() {
        return Err(format!("{what} {x} is not finite"));
    }
    let clamped = x.clamp(0.0, 1.0);
    if clamped != x {
        warn(format!("{what} {x} clamped to {clamped} (glTF allows [0, 1])"));
    }
    Ok(clamped)
}

/// Emitted radiance clamped at 0 from below, warning if it was negative.
fn clamp_emission(e: Rgb, warn: &mut impl FnMut(String)) -> Result<Rgb, String> {
    if e.iter().any(|x| !x.is_finite()) {
        return Err(format!("emission {} is not finite", fmt_rgb(e)));
    }
    let clamped = e.map(|x| x.max(0.0));
    if clamped != e {
        warn(format!("emission {} clamped to {}", fmt_rgb(e), fmt_rgb(clamped)));
    }
    Ok(clamped)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Converted piece by piece, a large image gives the bits of converting it whole and then
    /// box-filtering it (what the importer did before), for 8-bit and 16-bit images wider than a
    /// piece whose sides are not multiples of the factor.
    #[test]
    fn a_texture_converted_by_pieces_is_the_whole_image_filtered() {
        let (width, height) = (PIECE + 2 * MAX_TEXTURE_SIZE + 7, 302);
        let mut seed = 12345u64;
        let mut next = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 33) as u16
        };
        let rgb8 = image::RgbImage::from_fn(width, height, |_, _| {
            image::Rgb([next() as u8, next() as u8, next() as u8])
        });
        let rgb16 = image::ImageBuffer::<image::Rgb<u16>, _>::from_fn(width, height, |_, _| {
            image::Rgb([next(), next(), next()])
        });
        for image in [
            image::DynamicImage::ImageRgb8(rgb8),
            image::DynamicImage::ImageRgb16(rgb16),
        ] {
            let whole = linear_pixels(&image);
            let k = width.div_ceil(MAX_TEXTURE_SIZE);
            assert!(k > 1 && !width.is_multiple_of(k) && !height.is_multiple_of(k));
            let (w, h) = (width.div_ceil(k), height.div_ceil(k));
            let mut expected = vec![[0.0f32; 3]; (w * h) as usize];
            for y in 0..h {
                for x in 0..w {
                    let (mut sum, mut n) = ([0.0f64; 3], 0u32);
                    for sy in y * k..((y + 1) * k).min(height) {
                        for sx in x * k..((x + 1) * k).min(width) {
                            let c = whole[(sy * width + sx) as usize];
                            for i in 0..3 {
                                sum[i] += c[i] as f64;
                            }
                            n += 1;
                        }
                    }
                    expected[(y * w + x) as usize] = sum.map(|v| (v / n as f64) as f32);
                }
            }
            assert_eq!(linear_texture(&image), Some((w, h, expected)));
            // The mean, piece by piece, is the mean of every pixel in order.
            let mean = average_linear(&image).unwrap();
            let mut sum = [0.0f64; 3];
            let pixels: Vec<[f64; 3]> = match &image {
                image::DynamicImage::ImageRgb8(i) => (i.pixels())
                    .map(|p| p.0.map(|v| srgb_to_linear(v as f64 / 255.0)))
                    .collect(),
                _ => (image.to_rgb32f().pixels())
                    .map(|p| p.0.map(|v| srgb_to_linear(f64::from(v).clamp(0.0, 1.0))))
                    .collect(),
            };
            for p in &pixels {
                for i in 0..3 {
                    sum[i] += p[i];
                }
            }
            assert_eq!(mean, sum.map(|s| s / pixels.len() as f64));
        }
    }
}
