// The objects' shadows per texel (appended to field.wgsl and objects.wgsl): what every texel
// of the resident static charts loses to the objects (`shadow_loss` at the texel's centre),
// into `shadow_pool`, where the view and the gather read it bilinearly (`shadow_from_texels`).
// Run when the objects move or parts arrive, not every frame; mirrors as the view draws them.

// Per work item: a static surface and the first of the 64 texels of its chart the item covers.
@group(0) @binding(15) var<storage, read> texel_work: array<vec2<u32>>;

struct TexelParams {
    // How mirrors are read behind the objects: 1 from the field's rays, 0 traced `depth` deep.
    mode: u32,
    depth: u32,
    // 1: the shadows give back the objects' light (`object_light`, computed before).
    bounce: u32,
    // The objects' surfaces (`object_light_main`).
    object_surfaces: u32,
};

@group(0) @binding(16) var<uniform> texel_params: TexelParams;

@compute @workgroup_size(64)
fn shadow_texels_main(@builtin(workgroup_id) group: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let item = group.x + group.y * 65535u;
    if (item >= arrayLength(&texel_work)) {
        return;
    }
    let work = texel_work[item];
    let s = surfaces[work.x];
    let t = work.y + lane;
    let base = parts[s.part];
    if (t >= s.width * s.height || base == NONE) {
        return;
    }
    let x = f32(t % s.width) + 0.5;
    let y = f32(t / s.width) + 0.5;
    let p = s.grid_origin + (s.axis_u * x + s.axis_v * y) / s.inv_texel;
    let bounce = texel_params.bounce != 0u;
    // The gather's shadow, and with exact direct light the camera's too, without the direct
    // part (one call site: the driver inlines `shadow_loss` once).
    let kinds = select(1u, 2u, objects.camera_shadows != 0u);
    for (var k = 0u; k < kinds; k++) {
        let loss = shadow_loss(p, s.normal, s.diffuse, texel_params.mode, texel_params.depth, bounce, k == 0u).xyz;
        let i = select(objects.camera_shadows, 0u, k == 0u) + (base + s.texel_offset + t) * 3u;
        shadow_pool[i] = loss.x;
        shadow_pool[i + 1u] = loss.y;
        shadow_pool[i + 2u] = loss.z;
    }
}

// The light each object surface sends (`Gatherer::object_light`): ρd times the gather at its
// centroid, seeing the shadows of the texel pass before it. One invocation per surface.
@compute @workgroup_size(64)
fn object_light_main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x;
    if (i >= texel_params.object_surfaces) {
        return;
    }
    let s = surfaces[objects.first_surface + i];
    var centroid = vec3<f32>(0.0);
    for (var v = 0u; v < s.vertex_count; v++) {
        centroid += vertices[s.first_vertex + v].xyz;
    }
    centroid /= f32(s.vertex_count);
    let l = s.diffuse * incident(centroid, s.normal, texel_params.mode, texel_params.depth);
    object_light[3u * i] = l.x;
    object_light[3u * i + 1u] = l.y;
    object_light[3u * i + 2u] = l.z;
}
