//! The bytes of a glTF asset: the `.glb` container, buffers (the GLB binary
//! chunk, `data:` URIs, files next to the asset), accessors and images.
//!
//! Everything here is read defensively rather than through the `gltf`
//! crate's readers, which index slices without checking on malformed input
//! (an accessor of count 0, a GLB header shorter than itself, a sparse
//! accessor with too few values all panic there): every offset, length,
//! stride, index and count is checked, and a bad one is an error naming the
//! object it belongs to.

use std::path::{Component, Path, PathBuf};
use std::sync::Arc;

use ::gltf::json;
use base64::Engine;
use json::accessor::{ComponentType, Type};
use json::validation::Checked;

use crate::Error;

/// The glTF JSON and, for a `.glb`, its binary chunk.
pub(super) struct Container {
    pub json: json::Root,
    pub bin: Option<Vec<u8>>,
}

/// Reads a `.gltf` (JSON) or `.glb` (binary) file: a file that starts with
/// the GLB magic `glTF` is binary whatever its extension.
pub(super) fn read_container(bytes: &[u8], file: &str) -> Result<Container, Error> {
    let err = |msg: String| Error::scene(file, None, msg);
    let (json_bytes, bin) = if bytes.starts_with(b"glTF") {
        let (json, bin) = split_glb(bytes).map_err(|m| err(format!("malformed binary glTF (.glb): {m}")))?;
        (json, bin.map(<[u8]>::to_vec))
    } else {
        // A byte order mark is not JSON, but some writers put one.
        (bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes), None)
    };
    let json: json::Root = json::deserialize::from_slice(json_bytes).map_err(|e| {
        let what = if bin.is_some() || bytes.starts_with(b"glTF") {
            "the JSON chunk of the .glb"
        } else {
            "the glTF JSON"
        };
        if bin.is_none() && !bytes.starts_with(b"glTF") && file.to_ascii_lowercase().ends_with(".glb") {
            err(format!(
                "not a binary glTF: no 'glTF' magic at the start (and not JSON either: {e})"
            ))
        } else if e.is_syntax() || e.is_eof() {
            err(format!("{what} is not valid JSON: {e}"))
        } else {
            err(format!("{what} is not a valid glTF 2.0 document: {e}"))
        }
    })?;
    Ok(Container { json, bin })
}

/// The JSON chunk and the optional binary chunk of a GLB container
/// (header `glTF`, version 2, total length; then chunks, each a length, a
/// type and the data; the first one JSON). Chunks of unknown type are
/// skipped, as the specification asks.
fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), String> {
    let u32_at = |at: usize| -> Option<u32> {
        let b = bytes.get(at..at.checked_add(4)?)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    let (Some(version), Some(length)) = (u32_at(4), u32_at(8)) else {
        return Err(format!(
            "truncated: {} bytes, shorter than the 12-byte header",
            bytes.len()
        ));
    };
    if version != 2 {
        return Err(format!("version {version}, only glTF 2 is supported"));
    }
    let length = length as usize;
    if length > bytes.len() {
        return Err(format!(
            "truncated: the header says {length} bytes, the file has {}",
            bytes.len()
        ));
    }
    let mut at = 12;
    let mut json = None;
    let mut bin = None;
    while at < length {
        let (Some(chunk_length), Some(kind)) = (u32_at(at), bytes.get(at + 4..at + 8)) else {
            return Err(format!("truncated: a chunk header at byte {at} runs past the end"));
        };
        let start = at + 8;
        let Some(end) = start.checked_add(chunk_length as usize).filter(|&e| e <= length) else {
            return Err(format!(
                "truncated: the chunk at byte {at} says {chunk_length} bytes, only {} are left",
                length.saturating_sub(start)
            ));
        };
        let data = &bytes[start..end];
        match kind {
            b"JSON" if json.is_none() => json = Some(data),
            b"JSON" => return Err("a second JSON chunk".to_string()),
            b"BIN\0" if json.is_none() => return Err("the first chunk is not JSON".to_string()),
            b"BIN\0" if bin.is_none() => bin = Some(data),
            b"BIN\0" => return Err("a second BIN chunk".to_string()),
            _ if json.is_none() => return Err("the first chunk is not JSON".to_string()),
            _ => {}
        }
        // Chunks are padded to 4 bytes (the length includes the padding).
        at = end;
    }
    let json = json.ok_or_else(|| "no JSON chunk".to_string())?;
    Ok((json, bin))
}

/// The most accessor values an import decodes, all reads together: 2²⁸ (2 GiB as `f64`, each
/// read let go once its faces are made). Nodes that instance a mesh read its accessors again, so
/// a small file could ask for any number of reads of an accessor of 2²⁴ implicit zeros. A read
/// answered from the recent ones ([`RECENT_VALUES`]) is not counted: primitives that share one
/// vertex buffer, and the instances of a mesh, decode it once. A scene of
/// [`crate::scene::MAX_FACES`] faces decodes at most 15 values a face (triangles not indexed,
/// textured), about 1.3·10⁸.
pub const MAX_ACCESSOR_VALUES: u64 = 1 << 28;

/// The decoded accessors an import keeps for its next reads, the most recently read first, up to
/// 2²⁴ values in all (128 MiB): an accessor larger than that is decoded again at each read.
pub const RECENT_VALUES: usize = 1 << 24;

/// The buffers of an asset, read when first needed (a buffer no primitive
/// uses may be missing without consequence).
pub(super) struct Buffers {
    file: String,
    dir: PathBuf,
    bin: Option<Vec<u8>>,
    loaded: Vec<Option<Vec<u8>>>,
    /// Accessor values decoded so far ([`MAX_ACCESSOR_VALUES`]).
    values_read: u64,
    /// The accessors decoded last, as (index, what it was read as, values), most recent first
    /// ([`RECENT_VALUES`]).
    recent: std::collections::VecDeque<(usize, Expect, Arc<Vec<f64>>)>,
}

impl Buffers {
    pub fn new(file: &str, dir: &Path, bin: Option<Vec<u8>>, count: usize) -> Self {
        Buffers {
            file: file.to_string(),
            dir: dir.to_path_buf(),
            bin,
            loaded: vec![None; count],
            values_read: 0,
            recent: std::collections::VecDeque::new(),
        }
    }

    /// Accessor `index` as read as `expect` lately, if it still is among the recent ones (then
    /// the most recent).
    fn recent(&mut self, index: usize, expect: Expect) -> Option<Arc<Vec<f64>>> {
        let at = (self.recent.iter()).position(|(i, e, _)| (*i, *e) == (index, expect))?;
        let entry = self.recent.remove(at)?;
        let values = entry.2.clone();
        self.recent.push_front(entry);
        Some(values)
    }

    /// Keeps `values`, accessor `index` read as `expect`, among the recent ones, letting the
    /// oldest go past [`RECENT_VALUES`].
    fn remember(&mut self, index: usize, expect: Expect, values: Arc<Vec<f64>>) {
        if values.len() > RECENT_VALUES {
            return;
        }
        self.recent.push_front((index, expect, values));
        while self.recent.iter().map(|(_, _, v)| v.len()).sum::<usize>() > RECENT_VALUES {
            self.recent.pop_back();
        }
    }

    /// Counts `values` more accessor values read, or refuses them past [`MAX_ACCESSOR_VALUES`].
    fn charge(&mut self, values: u64) -> Result<(), String> {
        self.values_read = self.values_read.saturating_add(values);
        if self.values_read > MAX_ACCESSOR_VALUES {
            return Err(format!(
                "more than {MAX_ACCESSOR_VALUES} accessor values read in all (nodes that instance a mesh read it again)"
            ));
        }
        Ok(())
    }

    /// The bytes of buffer `index`, at least its `byteLength` long; the
    /// error names the buffer (the caller adds what needed it).
    pub fn get(&mut self, root: &json::Root, index: usize) -> Result<&[u8], String> {
        let err = |msg: String| format!("buffer {index}: {msg}");
        let Some(buffer) = root.buffers.get(index) else {
            return Err(err(format!("does not exist (the file has {})", root.buffers.len())));
        };
        if self.loaded[index].is_none() {
            let bytes = match &buffer.uri {
                Some(uri) => read_uri(&self.dir, uri).map_err(err)?,
                None if index == 0 => self.bin.take().ok_or_else(|| {
                    err("has no uri, and the file has no GLB binary chunk to stand for it".to_string())
                })?,
                None => {
                    return Err(err(
                        "has no uri (only buffer 0 of a .glb may use the binary chunk)".to_string()
                    ));
                }
            };
            let length = buffer.byte_length.0;
            if (bytes.len() as u64) < length {
                return Err(err(format!(
                    "byteLength is {length} but its data has only {} bytes",
                    bytes.len()
                )));
            }
            self.loaded[index] = Some(bytes);
        }
        Ok(self.loaded[index].as_deref().unwrap_or_default())
    }

    pub fn file(&self) -> &str {
        &self.file
    }
}

/// The bytes a URI names: a `data:` URI (base64 or percent-encoded), or a
/// relative path, resolved against the asset's folder.
pub(super) fn read_uri(dir: &Path, uri: &str) -> Result<Vec<u8>, String> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let Some((header, data)) = rest.split_once(',') else {
            return Err("malformed data URI: no ','".to_string());
        };
        return if header.ends_with(";base64") {
            let engine = base64::engine::GeneralPurpose::new(
                &base64::alphabet::STANDARD,
                base64::engine::GeneralPurposeConfig::new()
                    .with_decode_padding_mode(base64::engine::DecodePaddingMode::Indifferent),
            );
            engine
                .decode(data.trim())
                .map_err(|e| format!("malformed base64 in data URI: {e}"))
        } else {
            percent_decode(data)
        };
    }
    let path = resolve(dir, uri)?;
    std::fs::read(&path).map_err(|e| format!("cannot read '{uri}' ({}): {e}", path.display()))
}

/// A relative URI reference as a path under `dir`.
fn resolve(dir: &Path, uri: &str) -> Result<PathBuf, String> {
    Ok(dir.join(relative_path(uri)?))
}

/// A relative URI reference, percent-decoded, as a relative path. Schemes
/// (`http:`, `file:`), absolute paths and `..` are refused: an asset is
/// imported from its own folder only (a server imports uploads the same
/// way, and must not be made to read anything else).
pub(super) fn relative_path(uri: &str) -> Result<PathBuf, String> {
    let refused = |why: &str| {
        Err(format!(
            "'{uri}': {why}; only data: URIs and relative paths inside the asset's folder are supported"
        ))
    };
    let before_slash = uri.split('/').next().unwrap_or("");
    if before_slash.contains(':') {
        return refused("a URI with a scheme");
    }
    let decoded = percent_decode(uri).and_then(|b| String::from_utf8(b).map_err(|_| "not UTF-8".to_string()));
    let Ok(decoded) = decoded else {
        return refused("malformed percent-encoding");
    };
    if decoded.is_empty() {
        return refused("an empty path");
    }
    let relative = PathBuf::from(decoded);
    if relative
        .components()
        .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return refused("an absolute path or one that leaves the asset's folder");
    }
    Ok(relative)
}

fn percent_decode(s: &str) -> Result<Vec<u8>, String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' {
            let hex = bytes
                .get(i + 1..i + 3)
                .filter(|h| h.iter().all(u8::is_ascii_hexdigit))
                .and_then(|h| std::str::from_utf8(h).ok())
                .and_then(|h| u8::from_str_radix(h, 16).ok());
            let Some(b) = hex else {
                return Err(format!("malformed percent-encoding in '{s}'"));
            };
            out.push(b);
            i += 3;
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    Ok(out)
}

/// What an accessor must hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Expect {
    /// `VEC3` of any component type (`FLOAT`; integers with
    /// `KHR_mesh_quantization`, normalised or not).
    Positions,
    /// `SCALAR` of `UNSIGNED_BYTE`, `UNSIGNED_SHORT` or `UNSIGNED_INT`.
    Indices,
    /// `VEC2` of `FLOAT`, or of normalized `UNSIGNED_BYTE` / `UNSIGNED_SHORT` (glTF's
    /// `TEXCOORD_n`).
    TexCoords,
}

fn type_name(t: Type) -> &'static str {
    match t {
        Type::Scalar => "SCALAR",
        Type::Vec2 => "VEC2",
        Type::Vec3 => "VEC3",
        Type::Vec4 => "VEC4",
        Type::Mat2 => "MAT2",
        Type::Mat3 => "MAT3",
        Type::Mat4 => "MAT4",
    }
}

fn component_name(c: ComponentType) -> &'static str {
    match c {
        ComponentType::I8 => "BYTE",
        ComponentType::U8 => "UNSIGNED_BYTE",
        ComponentType::I16 => "SHORT",
        ComponentType::U16 => "UNSIGNED_SHORT",
        ComponentType::U32 => "UNSIGNED_INT",
        ComponentType::F32 => "FLOAT",
    }
}

fn component_size(c: ComponentType) -> u64 {
    c.size() as u64
}

/// Reads accessor `index` as numbers (`count × components` of them, in
/// order), checking it holds what `expect` says; decoded once while it stays among the recent
/// reads ([`RECENT_VALUES`]). `what` names its use in messages ("POSITION of mesh 'box' (#0)
/// primitive 1").
pub(super) fn read_accessor(
    root: &json::Root,
    buffers: &mut Buffers,
    index: usize,
    expect: Expect,
    what: &str,
) -> Result<Arc<Vec<f64>>, Error> {
    if let Some(values) = buffers.recent(index, expect) {
        return Ok(values);
    }
    let values = Arc::new(decode_accessor(root, buffers, index, expect, what)?);
    buffers.remember(index, expect, values.clone());
    Ok(values)
}

/// [`read_accessor`] decoding the accessor, whether or not it was read lately.
fn decode_accessor(
    root: &json::Root,
    buffers: &mut Buffers,
    index: usize,
    expect: Expect,
    what: &str,
) -> Result<Vec<f64>, Error> {
    let file = buffers.file().to_string();
    let err = |msg: String| Error::scene(&file, None, format!("{what}: accessor {index}: {msg}"));
    let Some(accessor) = root.accessors.get(index) else {
        return Err(err(format!("does not exist (the file has {})", root.accessors.len())));
    };
    let (Checked::Valid(ty), Checked::Valid(component)) = (accessor.type_, accessor.component_type) else {
        return Err(err("invalid type or componentType".to_string()));
    };
    let component = component.0;
    let fits = match expect {
        Expect::Positions => ty == Type::Vec3,
        Expect::Indices => {
            ty == Type::Scalar
                && !accessor.normalized
                && matches!(component, ComponentType::U8 | ComponentType::U16 | ComponentType::U32)
        }
        Expect::TexCoords => {
            ty == Type::Vec2
                && (component == ComponentType::F32
                    || (accessor.normalized && matches!(component, ComponentType::U8 | ComponentType::U16)))
        }
    };
    if !fits {
        let expected = match expect {
            Expect::Positions => "VEC3",
            Expect::Indices => "SCALAR of UNSIGNED_BYTE, UNSIGNED_SHORT or UNSIGNED_INT",
            Expect::TexCoords => "VEC2 of FLOAT, or of normalized UNSIGNED_BYTE or UNSIGNED_SHORT",
        };
        return Err(err(format!(
            "is {} of {}{}, expected {expected}",
            type_name(ty),
            component_name(component),
            if accessor.normalized { " (normalized)" } else { "" }
        )));
    }
    let components = ty.multiplicity() as u64;
    let count = accessor.count.0;
    buffers.charge(count.saturating_mul(components)).map_err(err)?;
    let layout = Layout {
        component,
        normalized: accessor.normalized,
        components,
    };
    let mut values = match accessor.buffer_view {
        Some(view) => read_view(
            root,
            buffers,
            view.value(),
            accessor.byte_offset.map_or(0, |o| o.0),
            count,
            layout,
        )
        .map_err(err)?,
        None => {
            // All zeros (then replaced by sparse values): no bytes bound
            // the count, so a sane limit does (16 Mi elements).
            if count > 1 << 24 {
                return Err(err(format!("count {count} without a bufferView is too large")));
            }
            vec![0.0; (count * components) as usize]
        }
    };
    if let Some(sparse) = &accessor.sparse {
        let n = sparse.count.0;
        let Checked::Valid(index_type) = sparse.indices.component_type else {
            return Err(err("sparse indices have an invalid componentType".to_string()));
        };
        let index_layout = Layout {
            component: index_type.0,
            normalized: false,
            components: 1,
        };
        let indices = read_view(
            root,
            buffers,
            sparse.indices.buffer_view.value(),
            sparse.indices.byte_offset.0,
            n,
            index_layout,
        )
        .map_err(|m| err(format!("sparse indices: {m}")))?;
        let replacements = read_view(
            root,
            buffers,
            sparse.values.buffer_view.value(),
            sparse.values.byte_offset.0,
            n,
            layout,
        )
        .map_err(|m| err(format!("sparse values: {m}")))?;
        let k = components as usize;
        for (i, &target) in indices.iter().enumerate() {
            if target >= count as f64 {
                return Err(err(format!("sparse index {target} is out of range (count {count})")));
            }
            let t = target as usize;
            values[t * k..(t + 1) * k].copy_from_slice(&replacements[i * k..(i + 1) * k]);
        }
    }
    Ok(values)
}

/// How the elements of an accessor are stored.
#[derive(Clone, Copy)]
struct Layout {
    component: ComponentType,
    normalized: bool,
    components: u64,
}

/// The bytes of buffer view `view_index`, checked to lie in its buffer.
fn view_bytes<'b>(root: &json::Root, buffers: &'b mut Buffers, view_index: usize) -> Result<&'b [u8], String> {
    let Some(view) = root.buffer_views.get(view_index) else {
        return Err(format!(
            "bufferView {view_index} does not exist (the file has {})",
            root.buffer_views.len()
        ));
    };
    let offset = view.byte_offset.map_or(0, |o| o.0);
    let length = view.byte_length.0;
    let buffer = view.buffer.value();
    let data = buffers.get(root, buffer)?;
    let range = offset
        .checked_add(length)
        .filter(|&end| end <= data.len() as u64)
        .map(|end| offset as usize..end as usize);
    range.map(|r| &data[r]).ok_or_else(|| {
        format!(
            "bufferView {view_index} (bytes {offset}..{offset}+{length}) lies outside buffer {buffer} ({} bytes)",
            data.len()
        )
    })
}

/// `count` elements from buffer view `view_index`, starting `offset` bytes
/// into it, every bound checked.
fn read_view(
    root: &json::Root,
    buffers: &mut Buffers,
    view_index: usize,
    offset: u64,
    count: u64,
    layout: Layout,
) -> Result<Vec<f64>, String> {
    let stride = root
        .buffer_views
        .get(view_index)
        .and_then(|v| v.byte_stride)
        .map(|s| s.0 as u64);
    let data = view_bytes(root, buffers, view_index)?;
    let size = component_size(layout.component);
    let element = size * layout.components;
    let stride = stride.unwrap_or(element);
    if stride < element {
        return Err(format!(
            "bufferView {view_index}: byteStride {stride} is smaller than an element ({element} bytes)"
        ));
    }
    let needed = match count {
        0 => Some(0),
        _ => stride
            .checked_mul(count - 1)
            .and_then(|b| b.checked_add(element))
            .and_then(|b| b.checked_add(offset)),
    };
    if needed.is_none_or(|n| n > data.len() as u64) {
        return Err(format!(
            "{count} elements of {element} bytes (stride {stride}) from byte {offset} do not fit \
             bufferView {view_index} ({} bytes)",
            data.len()
        ));
    }
    let mut values = Vec::with_capacity((count * layout.components) as usize);
    for e in 0..count {
        for c in 0..layout.components {
            // In range: offset + stride·e + size·(c + 1) ≤ needed ≤ data.len().
            let at = (offset + stride * e + size * c) as usize;
            values.push(component(&data[at..at + size as usize], layout));
        }
    }
    Ok(values)
}

/// One component, little-endian, as glTF's normalisation rules map it.
fn component(b: &[u8], layout: Layout) -> f64 {
    let n = layout.normalized;
    match layout.component {
        ComponentType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
        ComponentType::U32 => {
            let v = u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64;
            if n { v / u32::MAX as f64 } else { v }
        }
        ComponentType::U16 => {
            let v = u16::from_le_bytes([b[0], b[1]]) as f64;
            if n { v / 65535.0 } else { v }
        }
        ComponentType::I16 => {
            let v = i16::from_le_bytes([b[0], b[1]]) as f64;
            if n { (v / 32767.0).max(-1.0) } else { v }
        }
        ComponentType::U8 => {
            let v = b[0] as f64;
            if n { v / 255.0 } else { v }
        }
        ComponentType::I8 => {
            let v = b[0] as i8 as f64;
            if n { (v / 127.0).max(-1.0) } else { v }
        }
    }
}

/// The bytes of image `index`: its URI, or its buffer view.
pub(super) fn image_bytes(
    root: &json::Root,
    buffers: &mut Buffers,
    dir: &Path,
    index: usize,
) -> Result<Vec<u8>, String> {
    let Some(image) = root.images.get(index) else {
        return Err(format!(
            "image {index} does not exist (the file has {})",
            root.images.len()
        ));
    };
    match (&image.uri, image.buffer_view) {
        (Some(uri), _) => read_uri(dir, uri),
        (None, Some(view)) => view_bytes(root, buffers, view.value()).map(<[u8]>::to_vec),
        (None, None) => Err(format!("image {index} has neither a uri nor a bufferView")),
    }
}
