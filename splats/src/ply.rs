//! PLY import/export in the standard 3DGS layout (binary little-endian).
//!
//! Vertex properties written: `x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1
//! scale_2 rot_0 rot_1 rot_2 rot_3` (all `float`), where `f_dc` are SH degree-0 coefficients
//! (`colour = 0.5 + SH_C0 * f_dc`), `opacity` is the logit, `scale_*` are natural-log scales and
//! `rot_*` is the quaternion with w first. Normals are written as zeros.
//!
//! On import the property order may vary, any scalar type is accepted (converted to f32), and
//! extra properties (`f_rest_*`, normals, anything else) are read past and ignored. Elements
//! declared before `vertex` must have fixed-size rows (they are skipped). Errors name the header
//! line, the missing property or the truncated row; nothing panics on malformed input.

use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::Path;

use crate::cloud::GaussianCloud;

/// Zeroth-order real spherical-harmonic constant: `colour = 0.5 + SH_C0 * f_dc`.
pub const SH_C0: f32 = 0.282_094_8;

/// Header lines longer than this are rejected (guards against reading a binary file as text).
const MAX_HEADER_LINE_BYTES: usize = 4096;
/// Upper bound for the up-front allocation; larger files grow as rows arrive.
const MAX_PREALLOCATED_ROWS: usize = 1 << 20;

/// Why reading or writing a PLY file or stream failed.
#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    /// Opening, reading, writing or flushing failed (a short read of the data is
    /// [`Self::Truncated`] or [`Self::TruncatedElement`] instead).
    #[error("PLY I/O error: {0}")]
    Io(#[from] std::io::Error),
    /// The header is malformed or unsupported other than by its format (for example: no `ply`
    /// magic, an unknown line or property type, a list property before or in `vertex`, a line
    /// over 4096 bytes, no `end_header`, no `vertex` element).
    #[error("PLY header, line {line}: {message}")]
    Header {
        /// 1-based header line number; 0 when the problem is not on one line (no `vertex`
        /// element).
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// The `format` line names something other than `binary_little_endian 1.0` (its format
    /// and version, space-separated).
    #[error("unsupported PLY format `{0}` (only binary_little_endian 1.0 is supported)")]
    UnsupportedFormat(String),
    /// The vertex element lacks this property, one of `x y z f_dc_0..2 opacity scale_0..2
    /// rot_0..3`.
    #[error("PLY vertex element lacks the required property `{0}`")]
    MissingProperty(&'static str),
    /// The data ends before the last vertex row is complete.
    #[error("PLY data ends inside vertex row {row} of {count}, at property `{property}`")]
    Truncated {
        /// 0-based index of the incomplete vertex row.
        row: usize,
        /// Number of vertices the header declares.
        count: usize,
        /// The first property of that row not fully read (empty if none could be named).
        property: String,
    },
    /// The data ends inside an element declared before `vertex` (one being skipped).
    #[error("PLY data ends inside row {row} of element `{element}` that precedes the vertices")]
    TruncatedElement {
        /// The element's name in the header.
        element: String,
        /// 0-based index of the incomplete row.
        row: usize,
    },
    /// On write: the cloud's attribute vectors differ in length (the message of
    /// [`GaussianCloud::validate_lengths`]).
    #[error("GaussianCloud is inconsistent: {0}")]
    InvalidCloud(String),
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    /// Decodes a little-endian value; `bytes` has exactly `self.size()` bytes.
    fn decode(self, bytes: &[u8]) -> f32 {
        let array = |n: usize| {
            let mut out = [0u8; 8];
            out[..n].copy_from_slice(&bytes[..n]);
            out
        };
        match self {
            Self::I8 => f32::from(bytes[0] as i8),
            Self::U8 => f32::from(bytes[0]),
            Self::I16 => f32::from(i16::from_le_bytes([bytes[0], bytes[1]])),
            Self::U16 => f32::from(u16::from_le_bytes([bytes[0], bytes[1]])),
            Self::I32 => i32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as f32,
            Self::U32 => u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as f32,
            Self::F32 => f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]),
            Self::F64 => f64::from_le_bytes(array(8)) as f32,
        }
    }
}

struct Property {
    name: String,
    scalar: ScalarType,
    offset: usize,
}

struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
    row_bytes: usize,
}

/// The vertex properties we need, in the order of the `REQUIRED` table.
const REQUIRED: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
];

fn read_header(reader: &mut impl BufRead) -> Result<Vec<Element>, PlyError> {
    let mut line_number = 0usize;
    let mut next_line = |reader: &mut dyn BufRead| -> Result<(usize, String), PlyError> {
        let mut bytes = Vec::new();
        (&mut *reader)
            .take(MAX_HEADER_LINE_BYTES as u64 + 1)
            .read_until(b'\n', &mut bytes)?;
        line_number += 1;
        if bytes.is_empty() {
            return Err(PlyError::Header {
                line: line_number,
                message: "file ends before `end_header`".into(),
            });
        }
        if bytes.len() > MAX_HEADER_LINE_BYTES {
            return Err(PlyError::Header {
                line: line_number,
                message: "header line too long".into(),
            });
        }
        let text = String::from_utf8(bytes).map_err(|_| PlyError::Header {
            line: line_number,
            message: "header is not text".into(),
        })?;
        Ok((line_number, text.trim_end_matches(['\n', '\r']).to_string()))
    };
    let (line, magic) = next_line(reader)?;
    if magic.trim() != "ply" {
        return Err(PlyError::Header {
            line,
            message: format!("expected `ply`, found `{magic}`"),
        });
    }
    let mut elements: Vec<Element> = Vec::new();
    let mut saw_format = false;
    loop {
        let (line, text) = next_line(reader)?;
        let words: Vec<&str> = text.split_whitespace().collect();
        let header_error = |message: String| PlyError::Header { line, message };
        match words.as_slice() {
            [] => {}
            ["comment", ..] | ["obj_info", ..] => {}
            ["format", format, version] => {
                if *format != "binary_little_endian" || *version != "1.0" {
                    return Err(PlyError::UnsupportedFormat(format!("{format} {version}")));
                }
                saw_format = true;
            }
            ["element", name, count] => {
                let count = count
                    .parse::<usize>()
                    .map_err(|_| header_error(format!("bad element count `{count}`")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                    row_bytes: 0,
                });
            }
            ["property", "list", ..] => {
                let element = elements.last().map(|e| e.name.as_str()).unwrap_or("");
                if element == "vertex" || elements.iter().all(|e| e.name != "vertex") {
                    return Err(header_error(format!(
                        "list property in element `{element}` is not supported"
                    )));
                }
                // Lists after the vertex element are never read.
            }
            ["property", scalar, name] => {
                let scalar = ScalarType::parse(scalar).ok_or_else(|| {
                    header_error(format!("unknown property type `{scalar}` for `{name}`"))
                })?;
                let element = elements
                    .last_mut()
                    .ok_or_else(|| header_error(format!("property `{name}` before any element")))?;
                element.properties.push(Property {
                    name: name.to_string(),
                    scalar,
                    offset: element.row_bytes,
                });
                element.row_bytes += scalar.size();
            }
            ["end_header"] => break,
            _ => return Err(header_error(format!("unrecognised header line `{text}`"))),
        }
    }
    if !saw_format {
        return Err(PlyError::Header {
            line: line_number,
            message: "no `format` line".into(),
        });
    }
    Ok(elements)
}

/// Reads `buffer.len()` bytes; on a short read returns how many bytes arrived.
fn read_full(reader: &mut impl Read, buffer: &mut [u8]) -> Result<Result<(), usize>, PlyError> {
    let mut filled = 0;
    while filled < buffer.len() {
        match reader.read(&mut buffer[filled..]) {
            Ok(0) => return Ok(Err(filled)),
            Ok(n) => filled += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e.into()),
        }
    }
    Ok(Ok(()))
}

/// Parses a 3DGS PLY stream.
pub fn read_ply(reader: impl Read) -> Result<GaussianCloud, PlyError> {
    let mut reader = BufReader::new(reader);
    let elements = read_header(&mut reader)?;
    let vertex_position =
        elements
            .iter()
            .position(|e| e.name == "vertex")
            .ok_or(PlyError::Header {
                line: 0,
                message: "no `vertex` element".into(),
            })?;
    for element in &elements[..vertex_position] {
        let mut row = vec![0u8; element.row_bytes];
        for row_index in 0..element.count {
            if read_full(&mut reader, &mut row)?.is_err() {
                return Err(PlyError::TruncatedElement {
                    element: element.name.clone(),
                    row: row_index,
                });
            }
        }
    }
    let vertex = &elements[vertex_position];
    let mut layout = Vec::with_capacity(REQUIRED.len());
    for name in REQUIRED {
        let property = vertex
            .properties
            .iter()
            .find(|p| p.name == name)
            .ok_or(PlyError::MissingProperty(name))?;
        layout.push((property.offset, property.scalar));
    }
    let mut cloud = GaussianCloud::default();
    let capacity = vertex.count.min(MAX_PREALLOCATED_ROWS);
    cloud.means.reserve(capacity);
    cloud.log_scales.reserve(capacity);
    cloud.quaternions.reserve(capacity);
    cloud.opacity_logits.reserve(capacity);
    cloud.colours.reserve(capacity);
    let mut row = vec![0u8; vertex.row_bytes];
    let mut values = [0.0f32; REQUIRED.len()];
    for row_index in 0..vertex.count {
        if let Err(filled) = read_full(&mut reader, &mut row)? {
            let property = vertex
                .properties
                .iter()
                .find(|p| p.offset + p.scalar.size() > filled)
                .map(|p| p.name.clone())
                .unwrap_or_default();
            return Err(PlyError::Truncated {
                row: row_index,
                count: vertex.count,
                property,
            });
        }
        for (value, &(offset, scalar)) in values.iter_mut().zip(&layout) {
            *value = scalar.decode(&row[offset..offset + scalar.size()]);
        }
        let [x, y, z, dc0, dc1, dc2, opacity, s0, s1, s2, w, qx, qy, qz] = values;
        cloud.push(
            [x, y, z],
            [s0, s1, s2],
            [w, qx, qy, qz],
            opacity,
            [dc0, dc1, dc2].map(|dc| 0.5 + SH_C0 * dc),
        );
    }
    Ok(cloud)
}

/// Writes `cloud` as a 3DGS PLY stream.
pub fn write_ply(writer: impl Write, cloud: &GaussianCloud) -> Result<(), PlyError> {
    cloud.validate_lengths().map_err(PlyError::InvalidCloud)?;
    let mut writer = BufWriter::new(writer);
    writeln!(writer, "ply")?;
    writeln!(writer, "format binary_little_endian 1.0")?;
    writeln!(
        writer,
        "comment written by render-core (mac-ego3d); SH degree 0"
    )?;
    writeln!(writer, "element vertex {}", cloud.len())?;
    let names = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0",
        "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    for name in names {
        writeln!(writer, "property float {name}")?;
    }
    writeln!(writer, "end_header")?;
    for i in 0..cloud.len() {
        let [x, y, z] = cloud.means[i];
        let dc = cloud.colours[i].map(|c| (c - 0.5) / SH_C0);
        let [s0, s1, s2] = cloud.log_scales[i];
        let [w, qx, qy, qz] = cloud.quaternions[i];
        let row = [
            x,
            y,
            z,
            0.0,
            0.0,
            0.0,
            dc[0],
            dc[1],
            dc[2],
            cloud.opacity_logits[i],
            s0,
            s1,
            s2,
            w,
            qx,
            qy,
            qz,
        ];
        for value in row {
            writer.write_all(&value.to_le_bytes())?;
        }
    }
    writer.flush()?;
    Ok(())
}

/// Reads a 3DGS PLY file.
pub fn load_ply(path: impl AsRef<Path>) -> Result<GaussianCloud, PlyError> {
    read_ply(std::fs::File::open(path)?)
}

/// Writes a 3DGS PLY file, whole or not at all ([`geometry::files::write_whole`]).
pub fn save_ply(path: impl AsRef<Path>, cloud: &GaussianCloud) -> Result<(), PlyError> {
    geometry::files::write_whole(path.as_ref(), |file| write_ply(file, cloud))
}
