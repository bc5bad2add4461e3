//! Value codecs: how a slice of `f32` radiance becomes payload bytes and back.
//!
//! Three encodings of values exist (see [`crate::Encoding`]):
//!
//! * **F32** — the values' IEEE bits, lossless.
//! * **F16** — IEEE half precision (round to nearest even, via the `half` crate): half the size,
//!   relative error ≤ 2⁻¹¹ for normal values (|v| ≥ 2⁻¹⁴ ≈ 6.1e-5), absolute error ≤ 2⁻²⁵ below.
//!   Values whose magnitude rounds above 65504 cannot be stored and are refused at encode time.
//! * **RGB9E5** — three 9-bit mantissas sharing one 5-bit exponent in a `u32` per RGB triple
//!   (the OpenGL `EXT_texture_shared_exponent` format): a third of F32. The largest channel of a
//!   triple keeps a relative error ≤ 2⁻⁹; the others an absolute error ≤ 2⁻⁹ of the largest.
//!   Only 0 ≤ v ≤ 65408 is representable; negatives and larger values are refused at encode time.
//!
//! Before compression the element bytes are *shuffled* into planes (all first bytes, then all
//! second bytes, …). Neighbouring radiance values share sign, exponent and high mantissa bytes, so
//! the planes of high bytes are long runs that zstd compresses far better than interleaved bytes.

use half::f16;

/// Why a value could not be encoded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Unrepresentable {
    /// NaN or ±∞.
    NonFinite,
    /// Outside the range of the encoding (too large, or negative for RGB9E5).
    OutOfRange,
}

/// Returns the index and reason of the first value that cannot be stored, if any.
pub(crate) fn check_finite(values: &[f32]) -> Result<(), (usize, Unrepresentable)> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err((i, Unrepresentable::NonFinite)),
        None => Ok(()),
    }
}

/// F32 → little-endian bytes.
pub(crate) fn f32_to_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// Little-endian bytes → F32. `bytes.len()` must be a multiple of 4 (checked by the caller).
pub(crate) fn bytes_to_f32(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// F32 → F16 little-endian bytes; fails on the first value that would become ±∞ (or is NaN).
pub(crate) fn f32_to_f16_bytes(values: &[f32]) -> Result<Vec<u8>, (usize, Unrepresentable)> {
    check_finite(values)?;
    let mut out = Vec::with_capacity(values.len() * 2);
    for (i, &v) in values.iter().enumerate() {
        let h = f16::from_f32(v);
        if !h.is_finite() {
            return Err((i, Unrepresentable::OutOfRange));
        }
        out.extend_from_slice(&h.to_le_bytes());
    }
    Ok(out)
}

/// F16 little-endian bytes → F32. `bytes.len()` must be even (checked by the caller).
pub(crate) fn f16_bytes_to_f32(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(2)
        .map(|c| f16::from_le_bytes([c[0], c[1]]).to_f32())
        .collect()
}

/// Mantissa bits per channel of RGB9E5.
const RGB9E5_MANTISSA_BITS: i32 = 9;
/// Exponent bias of RGB9E5.
const RGB9E5_EXP_BIAS: i32 = 15;
/// Largest biased exponent of RGB9E5.
const RGB9E5_MAX_EXP: i32 = 31;
/// Largest value RGB9E5 can hold: 511/512 · 2¹⁶ = 65408.
pub(crate) const RGB9E5_MAX: f32 = 65408.0;

/// ⌊log₂ x⌋ for a positive finite f32, exactly (from the exponent bits; subnormals give -127,
/// far below anything RGB9E5 can represent, which is all the caller needs).
fn floor_log2(x: f32) -> i32 {
    ((x.to_bits() >> 23) & 0xff) as i32 - 127
}

/// 2^e as f32 for the small range RGB9E5 uses (-40 ≤ e ≤ 20): exact.
fn pow2(e: i32) -> f32 {
    (e as f32).exp2()
}

/// Packs one RGB triple (each channel in [0, 65408], checked by the caller).
fn pack_rgb9e5(rgb: [f32; 3]) -> u32 {
    let max = rgb[0].max(rgb[1]).max(rgb[2]);
    if max <= 0.0 {
        return 0;
    }
    let min_exp = -RGB9E5_EXP_BIAS - 1;
    let mut exp = floor_log2(max).max(min_exp) + 1 + RGB9E5_EXP_BIAS;
    let max_mantissa = (1u32 << RGB9E5_MANTISSA_BITS) as f32;
    // Rounding the largest channel may carry into a tenth bit: then use the next exponent.
    if (max / pow2(exp - RGB9E5_EXP_BIAS - RGB9E5_MANTISSA_BITS) + 0.5).floor() >= max_mantissa {
        exp += 1;
    }
    let exp = exp.clamp(0, RGB9E5_MAX_EXP);
    let scale = pow2(exp - RGB9E5_EXP_BIAS - RGB9E5_MANTISSA_BITS);
    let m = |v: f32| ((v / scale + 0.5).floor() as u32).min((1 << RGB9E5_MANTISSA_BITS) - 1);
    m(rgb[0]) | (m(rgb[1]) << 9) | (m(rgb[2]) << 18) | ((exp as u32) << 27)
}

/// Unpacks one RGB9E5 word; always finite and non-negative.
fn unpack_rgb9e5(word: u32) -> [f32; 3] {
    let exp = (word >> 27) as i32;
    let scale = pow2(exp - RGB9E5_EXP_BIAS - RGB9E5_MANTISSA_BITS);
    let m = |shift: u32| ((word >> shift) & 0x1ff) as f32 * scale;
    [m(0), m(9), m(18)]
}

/// F32 RGB triples (flattened; length a multiple of 3, checked by the caller) → RGB9E5 words,
/// little-endian.
pub(crate) fn f32_to_rgb9e5_bytes(values: &[f32]) -> Result<Vec<u8>, (usize, Unrepresentable)> {
    check_finite(values)?;
    if let Some(i) = values.iter().position(|&v| !(0.0..=RGB9E5_MAX).contains(&v)) {
        return Err((i, Unrepresentable::OutOfRange));
    }
    Ok(values
        .chunks_exact(3)
        .flat_map(|c| pack_rgb9e5([c[0], c[1], c[2]]).to_le_bytes())
        .collect())
}

/// RGB9E5 words (length a multiple of 4, checked by the caller) → flattened F32 RGB triples.
pub(crate) fn rgb9e5_bytes_to_f32(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .flat_map(|c| unpack_rgb9e5(u32::from_le_bytes([c[0], c[1], c[2], c[3]])))
        .collect()
}

/// Transposes `n` elements of `size` bytes into `size` planes of `n` bytes. A trailing partial
/// element (never produced by the encoders) is copied as is.
pub(crate) fn shuffle(bytes: &[u8], size: usize) -> Vec<u8> {
    if size <= 1 {
        return bytes.to_vec();
    }
    let n = bytes.len() / size;
    let mut out = vec![0u8; bytes.len()];
    for (i, element) in bytes.chunks_exact(size).enumerate() {
        for (plane, &b) in element.iter().enumerate() {
            out[plane * n + i] = b;
        }
    }
    out[n * size..].copy_from_slice(&bytes[n * size..]);
    out
}

/// Inverse of [`shuffle`].
pub(crate) fn unshuffle(bytes: &[u8], size: usize) -> Vec<u8> {
    if size <= 1 {
        return bytes.to_vec();
    }
    let n = bytes.len() / size;
    let mut out = vec![0u8; bytes.len()];
    for (i, element) in out.chunks_exact_mut(size).enumerate() {
        for (plane, b) in element.iter_mut().enumerate() {
            *b = bytes[plane * n + i];
        }
    }
    out[n * size..].copy_from_slice(&bytes[n * size..]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shuffle_round_trips_with_remainder() {
        let bytes: Vec<u8> = (0..23).collect();
        for size in 1..6 {
            assert_eq!(unshuffle(&shuffle(&bytes, size), size), bytes);
        }
    }

    #[test]
    fn rgb9e5_known_values() {
        assert_eq!(unpack_rgb9e5(pack_rgb9e5([0.0, 0.0, 0.0])), [0.0, 0.0, 0.0]);
        assert_eq!(unpack_rgb9e5(pack_rgb9e5([1.0, 0.5, 0.25])), [1.0, 0.5, 0.25]);
        assert_eq!(unpack_rgb9e5(pack_rgb9e5([RGB9E5_MAX; 3])), [RGB9E5_MAX; 3]);
        // Rounds up across a power of two without overflowing the mantissa.
        let [r, _, _] = unpack_rgb9e5(pack_rgb9e5([1.9999, 0.0, 0.0]));
        assert_eq!(r, 2.0);
    }

    #[test]
    fn rgb9e5_relative_error_of_the_largest_channel() {
        let mut worst = 0.0f32;
        let mut x = 1.0e-4f32;
        while x < 6.0e4 {
            let rgb = [x, x * 0.37, x * 0.011];
            let out = unpack_rgb9e5(pack_rgb9e5(rgb));
            worst = worst.max((out[0] - x).abs() / x);
            for c in 1..3 {
                assert!(
                    (out[c] - rgb[c]).abs() <= x * 2f32.powi(-9) * 1.0001,
                    "{rgb:?} -> {out:?}"
                );
            }
            x *= 1.013;
        }
        assert!(worst <= 2f32.powi(-9), "worst {worst}");
    }
}
