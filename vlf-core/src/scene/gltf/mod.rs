//! glTF 2.0 import (`.gltf` JSON with its buffers and images, or a binary
//! `.glb`): the asset is read into triangles and materials here, and
//! validated, split and normalised by [`build`](super::build) like any
//! other format.
//!
//! # Conventions
//!
//! * **What is imported.** Every mesh primitive of every node of the default
//!   scene (`scene`), else of scene 0, else of every node hierarchy if the
//!   file has no scene. Node transforms (`matrix`, or translation × rotation
//!   × scale) are composed down the hierarchy in f64. A node whose world
//!   transform mirrors (negative determinant) has its triangles' winding
//!   reversed, so that fronts stay fronts as glTF specifies. Skins, morph
//!   targets, cameras and punctual lights are ignored (with a warning:
//!   in the VLF only surfaces emit).
//! * **Primitives.** `TRIANGLES`, `TRIANGLE_STRIP` and `TRIANGLE_FAN`,
//!   indexed or not, become triangles; `POINTS` and the line modes are
//!   skipped with a warning. The winding is glTF's (counter-clockwise is
//!   the front), the same as OBJ's.
//! * **Materials** follow [`material`]: base colour → ρd, smooth metal →
//!   mirror, `emissiveFactor` × `KHR_materials_emissive_strength` → `Le`,
//!   a diffuser's base colour texture kept, with each triangle's
//!   `TEXCOORD_n` as a [`UvMap`], other textures averaged; a primitive without a material gets glTF's default
//!   material (a white diffuser), with a warning. Only the materials used
//!   are kept, in order of first use.
//! * **`doubleSided`** triangles are emitted twice, once per winding, so that
//!   both sides reflect, and, for an emitter, both sides emit (each side
//!   with the material's full radiance: a double-sided emitter emits twice
//!   the power of a one-sided one).
//! * **Faces.** Each triangle's [`FaceOrigin`] has line 0 and, as face, its
//!   running index among the file's triangles (both sides of a double-sided
//!   one share it); messages name it by mesh (name and index), primitive and
//!   triangle.
//! * **Required extensions** other than `KHR_materials_emissive_strength`,
//!   `KHR_mesh_quantization` and `KHR_texture_transform` (not applied:
//!   albedo textures are placed by their plain coordinates, with a warning)
//!   are errors naming the extension — notably the
//!   compressions `KHR_draco_mesh_compression` and `EXT_meshopt_compression`,
//!   whose data this importer cannot decode.
//! * **Bad input** is an error, never a panic: a truncated `.glb`, JSON that
//!   does not parse or is not glTF 2.0, a buffer whose file is missing or
//!   shorter than its `byteLength`, views and accessors outside their
//!   buffers, an accessor of the wrong type, an index out of range, a
//!   non-finite position or transform, a node hierarchy that is not a tree.
//!   External files must be relative paths inside the asset's folder (see
//!   `data::resolve`).

mod data;
mod material;
#[cfg(test)]
mod tests;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use ::gltf::json;
use glam::{DMat3, DMat4, DQuat, DVec2, DVec3};
use json::mesh::{Mode, Semantic};
use json::validation::Checked;

use self::data::{Buffers, Container, Expect, read_accessor, read_container};
use self::material::{Converted, Materials};
use super::build::{ImportOptions, MAX_FACES, Textured, Warnings, build_scene_named, check_options};
use super::{FaceOrigin, Material, Scene, UvMap};
use crate::Error;

/// Required extensions this importer honours.
const SUPPORTED_REQUIRED: &[&str] = &[
    "KHR_materials_emissive_strength",
    "KHR_mesh_quantization",
    "KHR_texture_transform",
];

/// Reads a glTF 2.0 file (`.gltf` or `.glb`) into a validated scene in the
/// VLF frame, following the conventions of the module documentation.
/// Returns the scene and the warnings (ignored features, approximated
/// materials, skipped degenerate triangles), which are also logged.
pub fn load_gltf(path: &Path, options: &ImportOptions) -> Result<(Scene, Vec<String>), Error> {
    check_options(options)?;
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let dir = path.parent().unwrap_or(Path::new(""));
    import(&bytes, &path.display().to_string(), dir, options)
}

/// The files a glTF asset refers to: its buffers' and images' relative URIs,
/// percent-decoded, as paths relative to the asset's folder, each once, in
/// order (`data:` URIs and a `.glb`'s binary chunk are no files). For tools
/// that copy or upload an asset with what it needs; a URI the importer
/// would refuse (absolute, `..`, a scheme) is an error here too.
pub fn gltf_external_files(path: &Path) -> Result<Vec<PathBuf>, Error> {
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let Container { json: root, .. } = read_container(&bytes, &file)?;
    let buffers = root.buffers.iter().filter_map(|b| b.uri.as_deref());
    let images = root.images.iter().filter_map(|i| i.uri.as_deref());
    let mut files: Vec<PathBuf> = Vec::new();
    for uri in buffers.chain(images).filter(|u| !u.starts_with("data:")) {
        let relative = data::relative_path(uri).map_err(|m| Error::scene(&file, None, m))?;
        if !files.contains(&relative) {
            files.push(relative);
        }
    }
    Ok(files)
}

/// [`load_gltf`] of a file's bytes: `file` names it in messages, `dir` is
/// where its relative URIs point.
fn import(bytes: &[u8], file: &str, dir: &Path, options: &ImportOptions) -> Result<(Scene, Vec<String>), Error> {
    let file = file.to_string();
    let Container { json: root, bin } = read_container(bytes, &file)?;
    let mut warnings = Warnings::default();
    check_asset(&root, &file, &mut warnings)?;
    if root.extensions_used.iter().any(|e| e == "KHR_texture_transform") {
        warnings.push(format!(
            "{file}: KHR_texture_transform is not applied: albedo textures are placed by their plain \
             texture coordinates"
        ));
    }

    let mut reader = Reader {
        root: &root,
        file: &file,
        buffers: Buffers::new(&file, dir, bin, root.buffers.len()),
        materials: Materials {
            root: &root,
            dir,
            averages: HashMap::new(),
            textures: Vec::new(),
            texture_of: HashMap::new(),
        },
        used: HashMap::new(),
        scene_materials: Vec::new(),
        polygons: Vec::new(),
        uvs: Vec::new(),
        primitives: Vec::new(),
        triangles: 0,
        visited: 0,
        warnings,
    };
    let roots = scene_roots(&root, &file, &mut reader.warnings)?;
    reader.walk(&roots)?;

    let Reader {
        polygons,
        uvs,
        primitives,
        scene_materials,
        materials,
        warnings,
        ..
    } = reader;
    let name_face = |o: &FaceOrigin| {
        let k = primitives.partition_point(|(first, _)| *first <= o.face);
        match k.checked_sub(1).and_then(|k| primitives.get(k)) {
            Some((first, label)) => format!("{label}, triangle {} (face #{})", o.face - first, o.face),
            None => format!("face #{}", o.face),
        }
    };
    let textured = Textured {
        textures: materials.textures,
        uvs,
    };
    // One list with the builder's warnings, where the two sides of a double-sided triangle
    // (which warn alike) are said once.
    build_scene_named(
        &polygons,
        scene_materials,
        options,
        &file,
        &name_face,
        textured,
        warnings,
    )
}

/// Checks the asset's version and extensions.
fn check_asset(root: &json::Root, file: &str, warnings: &mut Warnings) -> Result<(), Error> {
    let version = &root.asset.version;
    if version.split('.').next() != Some("2") {
        return Err(Error::scene(
            file,
            None,
            format!("glTF version {version} is not supported: only glTF 2.x"),
        ));
    }
    for ext in &root.extensions_required {
        if !SUPPORTED_REQUIRED.contains(&ext.as_str()) {
            let hint = if ext.contains("compression") {
                ": its compressed data cannot be decoded here; export without mesh compression"
            } else {
                ""
            };
            return Err(Error::scene(
                file,
                None,
                format!(
                    "the file requires extension {ext}, which is not supported{hint} (supported: {})",
                    SUPPORTED_REQUIRED.join(", ")
                ),
            ));
        }
    }
    if root.extensions_used.iter().any(|e| e == "KHR_lights_punctual") {
        warnings.push(format!(
            "{file}: KHR_lights_punctual lights ignored: only emissive surfaces emit in the VLF"
        ));
    }
    Ok(())
}

/// The nodes to import from: the default scene's, else scene 0's, else
/// every node that is no node's child.
fn scene_roots(root: &json::Root, file: &str, warnings: &mut Warnings) -> Result<Vec<usize>, Error> {
    if let Some(scene) = root.scene {
        let Some(s) = root.scenes.get(scene.value()) else {
            return Err(Error::scene(
                file,
                None,
                format!(
                    "the default scene {} does not exist (the file has {})",
                    scene.value(),
                    root.scenes.len()
                ),
            ));
        };
        return Ok(s.nodes.iter().map(|n| n.value()).collect());
    }
    if let Some(s) = root.scenes.first() {
        if root.scenes.len() > 1 {
            warnings.push(format!(
                "{file}: no default scene: scene 0 of {} is imported",
                root.scenes.len()
            ));
        }
        return Ok(s.nodes.iter().map(|n| n.value()).collect());
    }
    let mut child = vec![false; root.nodes.len()];
    for n in &root.nodes {
        for c in n.children.iter().flatten() {
            if let Some(flag) = child.get_mut(c.value()) {
                *flag = true;
            }
        }
    }
    Ok((0..root.nodes.len()).filter(|&n| !child[n]).collect())
}

/// A node's local transform, `None` if not finite or its rotation is zero.
fn local_transform(node: &json::Node) -> Option<DMat4> {
    let m = match node.matrix {
        Some(m) => DMat4::from_cols_array(&m.map(f64::from)),
        None => {
            let t = node.translation.unwrap_or([0.0; 3]).map(f64::from);
            let [x, y, z, w] = node.rotation.map_or([0.0, 0.0, 0.0, 1.0], |q| q.0).map(f64::from);
            let s = node.scale.unwrap_or([1.0; 3]).map(f64::from);
            let q = DQuat::from_xyzw(x, y, z, w);
            let length = q.length();
            if !(length.is_finite() && length > 0.0) {
                return None;
            }
            DMat4::from_scale_rotation_translation(DVec3::from(s), q / length, DVec3::from(t))
        }
    };
    m.is_finite().then_some(m)
}

/// The most primitives a file's nodes may instance, one per node and primitive of its mesh, of
/// any mode: 1 048 576. Each costs a label and its reads even when it makes no face (points,
/// lines, a strip of two vertices), and a file of a few hundred kilobytes may have 10⁴ nodes
/// instancing a mesh of 10⁴ primitives.
pub const MAX_PRIMITIVES: usize = 1 << 20;

/// The faces, materials and warnings gathered while walking the nodes.
struct Reader<'a> {
    root: &'a json::Root,
    file: &'a str,
    buffers: Buffers,
    materials: Materials<'a>,
    /// glTF material (`None`: the default one) → index into
    /// `scene_materials`, whether it is double-sided, and the texture coordinate set its
    /// albedo texture reads.
    used: HashMap<Option<usize>, (usize, bool, u32)>,
    scene_materials: Vec<Material>,
    polygons: Vec<(Vec<DVec3>, usize, FaceOrigin)>,
    /// Texture coordinates of each polygon, where its material has an albedo texture.
    uvs: Vec<Option<UvMap>>,
    /// First face of each primitive read, and its label for messages.
    primitives: Vec<(usize, String)>,
    /// Triangles read so far: the next one's face number.
    triangles: usize,
    /// Primitives visited so far, one per node that instances each ([`MAX_PRIMITIVES`]).
    visited: usize,
    warnings: Warnings,
}

impl Reader<'_> {
    fn fail(&self, msg: String) -> Error {
        Error::scene(self.file, None, msg)
    }

    /// Walks the hierarchies under `roots` depth first, in order, composing
    /// transforms.
    fn walk(&mut self, roots: &[usize]) -> Result<(), Error> {
        let mut visited = vec![false; self.root.nodes.len()];
        let mut stack: Vec<(usize, DMat4)> = roots.iter().rev().map(|&n| (n, DMat4::IDENTITY)).collect();
        while let Some((n, parent)) = stack.pop() {
            let Some(node) = self.root.nodes.get(n) else {
                return Err(self.fail(format!(
                    "node {n} does not exist (the file has {})",
                    self.root.nodes.len()
                )));
            };
            if std::mem::replace(&mut visited[n], true) {
                return Err(self.fail(format!(
                    "node {n} is reached twice: the node hierarchy must be a tree (no node with two \
                     parents, no cycle, no scene listing a node twice)"
                )));
            }
            let label = match &node.name {
                Some(name) => format!("node '{name}' (#{n})"),
                None => format!("node #{n}"),
            };
            let local =
                local_transform(node).ok_or_else(|| self.fail(format!("{label}: its transform is not finite")))?;
            let world = parent * local;
            if let Some(mesh) = node.mesh {
                if node.skin.is_some() {
                    self.warnings.push(format!(
                        "{}: {label}: skin ignored: the mesh is imported in its rest pose",
                        self.file
                    ));
                }
                self.mesh(mesh.value(), &world, &label)?;
            }
            for c in node.children.iter().flatten().rev() {
                stack.push((c.value(), world));
            }
        }
        Ok(())
    }

    /// The triangles of mesh `index` under the world transform `world`.
    fn mesh(&mut self, index: usize, world: &DMat4, node: &str) -> Result<(), Error> {
        let root = self.root;
        let Some(mesh) = root.meshes.get(index) else {
            return Err(self.fail(format!(
                "{node}: mesh {index} does not exist (the file has {})",
                root.meshes.len()
            )));
        };
        let mesh_label = match &mesh.name {
            Some(name) => format!("mesh '{name}' (#{index})"),
            None => format!("mesh #{index}"),
        };
        let flip = DMat3::from_mat4(*world).determinant() < 0.0;
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            self.visited += 1;
            if self.visited > MAX_PRIMITIVES {
                return Err(self.fail(format!(
                    "{node}: more than {MAX_PRIMITIVES} primitives, counting one per node that instances each"
                )));
            }
            let label = format!("{mesh_label} primitive {p}");
            let Checked::Valid(mode) = primitive.mode else {
                return Err(self.fail(format!("{label}: invalid mode")));
            };
            if matches!(mode, Mode::Points | Mode::Lines | Mode::LineLoop | Mode::LineStrip) {
                self.warnings.push(format!(
                    "{}: {label}: mode {mode:?} ignored: only triangles are surfaces",
                    self.file
                ));
                continue;
            }
            if primitive.targets.as_ref().is_some_and(|t| !t.is_empty()) {
                self.warnings
                    .push(format!("{}: {label}: morph targets ignored", self.file));
            }
            let Some(position) = primitive.attributes.get(&Checked::Valid(Semantic::Positions)) else {
                return Err(self.fail(format!("{label}: no POSITION attribute")));
            };
            let positions = read_accessor(
                root,
                &mut self.buffers,
                position.value(),
                Expect::Positions,
                &format!("POSITION of {label}"),
            )?;
            let positions: Vec<DVec3> = positions
                .chunks_exact(3)
                .map(|c| DVec3::new(c[0], c[1], c[2]))
                .collect();
            if let Some((i, p)) = positions.iter().enumerate().find(|(_, p)| !p.is_finite()) {
                return Err(self.fail(format!("{label}: POSITION {i} is not finite: {p}")));
            }
            let indices: Vec<usize> = match primitive.indices {
                Some(accessor) => {
                    let what = format!("indices of {label}");
                    let indices = read_accessor(root, &mut self.buffers, accessor.value(), Expect::Indices, &what)?;
                    let n = positions.len();
                    if let Some((i, v)) = indices.iter().enumerate().find(|(_, v)| **v >= n as f64) {
                        return Err(self.fail(format!(
                            "{label}: index {v} (element {i} of the indices) is out of range: POSITION has {n} vertices"
                        )));
                    }
                    indices.iter().map(|&v| v as usize).collect()
                }
                None => (0..positions.len()).collect(),
            };
            let triangles = match mode {
                Mode::Triangles => {
                    if !indices.len().is_multiple_of(3) {
                        return Err(self.fail(format!(
                            "{label}: {} vertices, not a multiple of 3 for TRIANGLES",
                            indices.len()
                        )));
                    }
                    indices.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect()
                }
                // glTF: triangle i is (i, i+1, i+2), with i+1 and i+2
                // swapped for odd i so that all keep one orientation.
                Mode::TriangleStrip => (0..indices.len().saturating_sub(2))
                    .map(|i| {
                        let (a, b, c) = (indices[i], indices[i + 1], indices[i + 2]);
                        if i % 2 == 0 { [a, b, c] } else { [a, c, b] }
                    })
                    .collect(),
                Mode::TriangleFan => (1..indices.len().saturating_sub(1))
                    .map(|i| [indices[i], indices[i + 1], indices[0]])
                    .collect(),
                _ => Vec::new(),
            };
            let (material, double_sided, tex_coord) = self.material(primitive.material.map(|m| m.value()), &label)?;
            let texcoords = if self.scene_materials[material].albedo_texture.is_some() {
                match primitive
                    .attributes
                    .get(&Checked::Valid(Semantic::TexCoords(tex_coord)))
                {
                    Some(accessor) => {
                        let what = format!("TEXCOORD_{tex_coord} of {label}");
                        let uv = read_accessor(root, &mut self.buffers, accessor.value(), Expect::TexCoords, &what)?;
                        let uv: Vec<DVec2> = uv.chunks_exact(2).map(|c| DVec2::new(c[0], c[1])).collect();
                        if uv.len() != positions.len() {
                            return Err(self.fail(format!(
                                "{what}: {} coordinates for {} vertices",
                                uv.len(),
                                positions.len()
                            )));
                        }
                        if let Some((i, t)) = uv.iter().enumerate().find(|(_, t)| !t.is_finite()) {
                            return Err(self.fail(format!("{what}: coordinate {i} is not finite: {t}")));
                        }
                        Some(uv)
                    }
                    None => {
                        self.warnings.push(format!(
                            "{}: {label} has no TEXCOORD_{tex_coord} for its material's texture: \
                             the texture's mean colour is used",
                            self.file
                        ));
                        None
                    }
                }
            } else {
                None
            };
            let faces = triangles.len() * if double_sided { 2 } else { 1 };
            if self.polygons.len() + faces > MAX_FACES {
                return Err(self.fail(format!(
                    "{label}: {faces} more faces, after {} already read: a scene has at most {MAX_FACES}",
                    self.polygons.len()
                )));
            }
            self.primitives.push((self.triangles, label));
            self.add(
                &triangles,
                &positions,
                texcoords.as_deref(),
                world,
                flip,
                material,
                double_sided,
            );
        }
        Ok(())
    }

    /// Adds triangles (indices into `positions`, and into `uv` where given) as faces.
    #[allow(clippy::too_many_arguments)]
    fn add(
        &mut self,
        triangles: &[[usize; 3]],
        positions: &[DVec3],
        uv: Option<&[DVec2]>,
        world: &DMat4,
        flip: bool,
        material: usize,
        double_sided: bool,
    ) {
        for t in triangles {
            let corners = t.map(|i| world.transform_point3(positions[i]));
            // The map is affine over the triangle's plane, so it does not care about winding.
            let map = uv.and_then(|uv| UvMap::from_triangle(corners, t.map(|i| uv[i])));
            let [a, b, c] = corners;
            let front = if flip { [a, c, b] } else { [a, b, c] };
            let origin = FaceOrigin {
                line: 0,
                face: self.triangles,
            };
            self.polygons.push((front.to_vec(), material, origin.clone()));
            self.uvs.push(map);
            if double_sided {
                let [a, b, c] = front;
                self.polygons.push((vec![a, c, b], material, origin));
                self.uvs.push(map);
            }
            self.triangles += 1;
        }
    }

    /// The scene's index of glTF material `index` (`None`: the default
    /// material), converting it on first use, and whether it is
    /// double-sided.
    fn material(&mut self, index: Option<usize>, primitive: &str) -> Result<(usize, bool, u32), Error> {
        if index.is_none() {
            self.warnings.push(format!(
                "{}: {primitive} has no material: glTF's default material is used (a white diffuser, ρd = 1)",
                self.file
            ));
        }
        if let Some(&known) = self.used.get(&index) {
            return Ok(known);
        }
        let Converted {
            material,
            double_sided,
            tex_coord,
        } = match index {
            Some(k) => self.materials.convert(&mut self.buffers, k, &mut self.warnings)?,
            None => Materials::default_material(),
        };
        let entry = (self.scene_materials.len(), double_sided, tex_coord);
        self.scene_materials.push(material);
        self.used.insert(index, entry);
        Ok(entry)
    }
}
