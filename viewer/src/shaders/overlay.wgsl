// The status line: a string drawn with the 8×8 bitmap font of `font8x8` (basic Latin) in the
// top-left corner, white on a translucent black band.

struct Params {
    // Top-left corner of the text, in pixels.
    origin: vec2<f32>,
    // Screen pixels per font pixel.
    scale: f32,
    // Characters in `text`.
    count: u32,
    // The target's size in pixels.
    screen: vec2<f32>,
    _pad: vec2<f32>,
};

@group(0) @binding(0) var<uniform> params: Params;
// 128 glyphs of 8 rows, one byte a row (bit 0 the leftmost pixel), packed 4 rows a word.
@group(0) @binding(1) var<storage, read> glyphs: array<u32>;
// The characters, one a word.
@group(0) @binding(2) var<storage, read> text: array<u32>;

const PAD: f32 = 2.0;

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    // Two triangles over the band around the text.
    let corner = array<vec2<f32>, 6>(
        vec2<f32>(0.0, 0.0), vec2<f32>(1.0, 0.0), vec2<f32>(0.0, 1.0),
        vec2<f32>(1.0, 0.0), vec2<f32>(1.0, 1.0), vec2<f32>(0.0, 1.0),
    )[i];
    let size = vec2<f32>(f32(params.count) * 8.0 * params.scale, 8.0 * params.scale) + 2.0 * PAD;
    let p = params.origin - PAD + corner * size;
    return vec4<f32>(p.x / params.screen.x * 2.0 - 1.0, 1.0 - p.y / params.screen.y * 2.0, 0.0, 1.0);
}

@fragment
fn fs_main(@builtin(position) position: vec4<f32>) -> @location(0) vec4<f32> {
    let background = vec4<f32>(0.0, 0.0, 0.0, 0.6);
    let p = floor((position.xy - params.origin) / params.scale);
    if (p.x < 0.0 || p.y < 0.0 || p.y >= 8.0 || p.x >= f32(params.count) * 8.0) {
        return background;
    }
    let column = u32(p.x);
    let row = u32(p.y);
    let code = text[column / 8u] & 127u;
    let byte = (glyphs[code * 2u + row / 4u] >> ((row % 4u) * 8u)) & 255u;
    if (((byte >> (column % 8u)) & 1u) != 0u) {
        return vec4<f32>(1.0, 1.0, 1.0, 1.0);
    }
    return background;
}
