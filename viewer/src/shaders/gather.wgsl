// The gather as a compute pass (appended to field.wgsl and objects.wgsl, whose bindings and
// functions it uses): `incident` at each of a list of points, one invocation per point, as
// `vlf_core::dynamic::gather::Gatherer::incident` computes it on the CPU.

struct GatherParams {
    points: u32,
    // How mirrors are read: 1 from the field's rays, 0 traced `depth` deep.
    mode: u32,
    depth: u32,
    _pad: u32,
};

@group(0) @binding(15) var<uniform> gather_params: GatherParams;
// Per point: its position (xyz), its unit normal (xyz) and a reflectance (xyz), three vec4
// each, in the VLF frame.
@group(0) @binding(16) var<storage, read> gather_points: array<vec4<f32>>;
// Per point: the gathered radiance (xyz), or the shadow's loss (xyz, w 1 where any).
@group(0) @binding(17) var<storage, read_write> gathered: array<vec4<f32>>;

@compute @workgroup_size(64)
fn gather_main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x;
    if (i >= gather_params.points) {
        return;
    }
    let p = gather_points[3u * i].xyz;
    let n = normalize(gather_points[3u * i + 1u].xyz);
    gathered[i] = vec4<f32>(incident(p, n, gather_params.mode, gather_params.depth), 0.0);
}

// The radiance static diffuse points lose to the objects (`shadow_loss`).
@compute @workgroup_size(64)
fn shadow_main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x;
    if (i >= gather_params.points) {
        return;
    }
    let p = gather_points[3u * i].xyz;
    let n = normalize(gather_points[3u * i + 1u].xyz);
    let rho = gather_points[3u * i + 2u].xyz;
    gathered[i] = shadow_loss(p, n, rho, gather_params.mode, gather_params.depth, objects.bounce_light != 0u, true);
}
