// The gather on the GPU (appended to field.wgsl, whose bindings and functions it uses): the
// light arriving at points of dynamic objects, as `vlf_core::dynamic::gather::Gatherer::incident`
// computes it on the CPU,
//
//     E = Σ_d L_in(±ω_d) |n·ω_d| Δω_d / Σ_d |n·ω_d| Δω_d,
//
// where L_in is what the static surface seen along ω (the one on n's side of the line ±ω_d)
// sends back, read from the field's maps (mirrors as `mode` says), and nothing where a dynamic
// object is nearer. One invocation per point.

struct GatherParams {
    points: u32,
    directions: u32,
    // The objects' BVH root among `nodes`, NONE when there are none.
    objects_root: u32,
    // How mirrors are read: 1 from the field's rays, 0 traced `depth` deep.
    mode: u32,
    depth: u32,
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
};

@group(0) @binding(8) var<uniform> gather_params: GatherParams;
// Per point: its position (xyz) and its unit normal (xyz), two vec4 each, in the VLF frame.
@group(0) @binding(9) var<storage, read> gather_points: array<vec4<f32>>;
// Per line direction: its unit vector (xyz) and its weight Δω (w).
@group(0) @binding(10) var<storage, read> gather_directions: array<vec4<f32>>;
// Per point: the gathered radiance (xyz).
@group(0) @binding(11) var<storage, read_write> gathered: array<vec4<f32>>;

// Radiance arriving at `o` from −d (looking along d): the static surface's, or nothing where
// an object is nearer or nothing is hit.
fn arriving(o: vec3<f32>, d: vec3<f32>) -> vec3<f32> {
    let hit = trace_from(0u, o, d, 0.0, 3.4e38);
    if (hit.surface == NONE || !hit.front) {
        return vec3<f32>(0.0);
    }
    if (gather_params.objects_root != NONE) {
        let blocker = trace_from(gather_params.objects_root, o, d, 0.0, hit.t);
        if (blocker.surface != NONE) {
            return vec3<f32>(0.0);
        }
    }
    let s = surfaces[hit.surface];
    let p = o + hit.t * d;
    return shade(s, p, d, diffuse_at(s, p), gather_params.mode, gather_params.depth);
}

@compute @workgroup_size(64)
fn gather_main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x;
    if (i >= gather_params.points) {
        return;
    }
    let p = gather_points[2u * i].xyz;
    let n = normalize(gather_points[2u * i + 1u].xyz);
    let origin = p + n * RAY_EPSILON;
    var sum = vec3<f32>(0.0);
    var weights = 0.0;
    for (var k = 0u; k < gather_params.directions; k++) {
        let direction = gather_directions[k];
        let c = dot(n, direction.xyz);
        if (c == 0.0) {
            continue;
        }
        let d = select(-direction.xyz, direction.xyz, c > 0.0);
        let w = abs(c) * direction.w;
        weights += w;
        sum += arriving(origin, d) * w;
    }
    if (weights > 0.0) {
        sum /= weights;
    }
    gathered[i] = vec4<f32>(sum, 0.0);
}
