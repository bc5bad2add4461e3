// Draws a light field's diffuse surfaces (and emitters) with their radiance maps.
//
// Every surface owns a rectangular grid of texels in one global atlas (see
// `vlf_core::maps`): texel (s, t) of surface i is `radiance[first_i + t·width_i + s]`.
// A fragment reads the outgoing radiance bilinearly between texel centres,
// clamping at the grid's border, exactly as `LightField::radiance_at` does on
// the CPU. The texel coordinates (already shifted by ½ to texel centres) are
// computed per vertex in f64 on the CPU: they are affine on the polygon's
// plane, so perspective-correct interpolation reproduces them exactly.
//
// Back faces are drawn black: they still hide what lies behind them, as a
// back-face hit does for the CPU renderer's rays.

struct View {
    // VLF frame → clip space, sub-pixel jitter included.
    clip_from_vlf: mat4x4<f32>,
};

struct Grid {
    first: u32,
    width: u32,
    height: u32,
    _pad: u32,
};

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<storage, read> grids: array<Grid>;
// Radiance of every atlas texel, RGB packed tightly (3 floats per texel).
@group(0) @binding(2) var<storage, read> radiance: array<f32>;

struct VertexIn {
    @location(0) position: vec3<f32>,
    @location(1) texel: vec2<f32>,
    @location(2) surface: u32,
};

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) texel: vec2<f32>,
    @location(1) @interpolate(flat) surface: u32,
};

@vertex
fn vs_main(v: VertexIn) -> VertexOut {
    var out: VertexOut;
    out.clip = view.clip_from_vlf * vec4<f32>(v.position, 1.0);
    out.texel = v.texel;
    out.surface = v.surface;
    return out;
}

fn texel_radiance(g: Grid, x: u32, y: u32) -> vec3<f32> {
    let i = (g.first + y * g.width + x) * 3u;
    return vec3<f32>(radiance[i], radiance[i + 1u], radiance[i + 2u]);
}

@fragment
fn fs_main(in: VertexOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    if (!front) {
        return vec4<f32>(0.0, 0.0, 0.0, 1.0);
    }
    let g = grids[in.surface];
    let c0 = floor(in.texel);
    let f = in.texel - c0;
    let hi = vec2<f32>(f32(g.width - 1u), f32(g.height - 1u));
    let a = vec2<u32>(clamp(c0, vec2<f32>(0.0), hi));
    let b = vec2<u32>(clamp(c0 + 1.0, vec2<f32>(0.0), hi));
    let l = texel_radiance(g, a.x, a.y) * ((1.0 - f.x) * (1.0 - f.y))
          + texel_radiance(g, b.x, a.y) * (f.x * (1.0 - f.y))
          + texel_radiance(g, a.x, b.y) * ((1.0 - f.x) * f.y)
          + texel_radiance(g, b.x, b.y) * (f.x * f.y);
    return vec4<f32>(l, 1.0);
}
