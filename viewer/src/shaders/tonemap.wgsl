// Tone mapping for the screen: the linear radiance frame scaled by 2^exposure, clamped to [0, 1]
// and sRGB-encoded — `vlf_core::render::image::tone_map`, the CPU's PNG output. On an sRGB
// surface the hardware encodes; otherwise `params.encode` asks the shader to.

struct Params {
    scale: f32,
    encode: u32,
    _pad0: u32,
    _pad1: u32,
};

@group(0) @binding(0) var frame: texture_2d<f32>;
@group(0) @binding(1) var<uniform> params: Params;

// One triangle covering the screen.
@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let x = f32((i << 1u) & 2u) * 2.0 - 1.0;
    let y = f32(i & 2u) * 2.0 - 1.0;
    return vec4<f32>(x, y, 0.0, 1.0);
}

fn srgb_oetf(v: f32) -> f32 {
    if (v <= 0.0031308) {
        return 12.92 * v;
    }
    return 1.055 * pow(v, 1.0 / 2.4) - 0.055;
}

@fragment
fn fs_main(@builtin(position) position: vec4<f32>) -> @location(0) vec4<f32> {
    let linear = textureLoad(frame, vec2<i32>(position.xy), 0).rgb * params.scale;
    var c = clamp(linear, vec3<f32>(0.0), vec3<f32>(1.0));
    if (params.encode != 0u) {
        c = vec3<f32>(srgb_oetf(c.r), srgb_oetf(c.g), srgb_oetf(c.b));
    }
    return vec4<f32>(c, 1.0);
}
