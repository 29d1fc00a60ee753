//! PLY input (point clouds) and output (known voxels).
//!
//! Reading accepts `binary_little_endian` and `ascii` files whose `vertex` element has `x`, `y`,
//! `z` properties of any scalar type (extra scalar properties are skipped; list properties only in
//! other elements, which are skipped). A header line `comment origin X Y Z` gives the sensor origin.
//!
//! Writing produces `binary_little_endian` with one vertex per known voxel: float `x`, `y`, `z`
//! (voxel centre), float `occupancy` and `roi` (log-odds).

use std::io::{BufRead, BufReader, Read, Write};

use nalgebra::Point3;

use crate::RoiMap;

/// Errors reading a PLY cloud.
#[derive(thiserror::Error, Debug)]
pub enum PlyError {
    #[error("I/O error: {0}")]
    Io(#[from] std::io::Error),
    #[error("not a PLY file")]
    NotPly,
    #[error("unsupported PLY format `{0}` (binary_little_endian and ascii are read)")]
    UnsupportedFormat(String),
    #[error("bad PLY header: {0}")]
    BadHeader(String),
    #[error("PLY has no vertex element with float x, y, z")]
    NoXyz,
    #[error("PLY data ends early: {0}")]
    Truncated(String),
    #[error("bad PLY value: {0}")]
    BadValue(String),
}

/// A point cloud read from PLY.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlyCloud {
    pub points: Vec<Point3<f32>>,
    /// From a `comment origin X Y Z` header line.
    pub origin: Option<Point3<f64>>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn read_le(self, b: &[u8]) -> f64 {
        match self {
            Scalar::I8 => f64::from(b[0] as i8),
            Scalar::U8 => f64::from(b[0]),
            Scalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Scalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Scalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F64 => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
        }
    }
}

#[derive(Debug)]
enum Property {
    Scalar(String, Scalar),
    List(Scalar),
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

fn next_line(r: &mut impl BufRead, line: &mut String) -> Result<(), PlyError> {
    line.clear();
    if r.read_line(line)? == 0 {
        return Err(PlyError::BadHeader("ends before end_header".into()));
    }
    Ok(())
}

/// Reads a PLY point cloud (see the module docs).
pub fn read_cloud(r: impl Read) -> Result<PlyCloud, PlyError> {
    let mut r = BufReader::new(r);
    let header = read_header(&mut r)?;
    let vertex_at = header
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or(PlyError::NoXyz)?;
    let (before, vertex) = (&header.elements[..vertex_at], &header.elements[vertex_at]);
    let xyz = xyz_of(vertex)?;
    let points = match header.binary {
        true => read_binary_vertices(&mut r, before, vertex, xyz)?,
        false => read_ascii_vertices(r, before, vertex, xyz)?,
    };
    Ok(PlyCloud {
        points,
        origin: header.origin,
    })
}

/// What a PLY header declares.
struct Header {
    /// Binary little-endian (else ASCII).
    binary: bool,
    origin: Option<Point3<f64>>,
    elements: Vec<Element>,
}

/// The header, up to and including `end_header`.
fn read_header(r: &mut impl BufRead) -> Result<Header, PlyError> {
    let mut line = String::new();
    next_line(r, &mut line)?;
    if line.trim_end() != "ply" {
        return Err(PlyError::NotPly);
    }
    let (mut binary, mut origin, mut elements) = (None, None, Vec::new());
    loop {
        next_line(r, &mut line)?;
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["end_header"] => break,
            ["format", fmt, _version] => binary = Some(is_binary(fmt)?),
            ["comment", "origin", x, y, z] => origin = Some(parse_origin([x, y, z])?),
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, count] => elements.push(Element {
                name: name.to_string(),
                count: count
                    .parse()
                    .map_err(|_| PlyError::BadHeader(format!("bad count `{count}`")))?,
                props: Vec::new(),
            }),
            ["property", rest @ ..] => add_property(&mut elements, rest, &line)?,
            _ => {
                return Err(PlyError::BadHeader(format!(
                    "unexpected line `{}`",
                    line.trim()
                )))
            }
        }
    }
    let binary = binary.ok_or_else(|| PlyError::BadHeader("no format line".into()))?;
    Ok(Header {
        binary,
        origin,
        elements,
    })
}

fn is_binary(format: &str) -> Result<bool, PlyError> {
    match format {
        "binary_little_endian" => Ok(true),
        "ascii" => Ok(false),
        other => Err(PlyError::UnsupportedFormat(other.to_string())),
    }
}

fn parse_origin(xyz: [&&str; 3]) -> Result<Point3<f64>, PlyError> {
    let p = |s: &str| {
        s.parse::<f64>()
            .map_err(|_| PlyError::BadHeader(format!("bad origin value `{s}`")))
    };
    Ok(Point3::new(p(xyz[0])?, p(xyz[1])?, p(xyz[2])?))
}

/// A `property` line's words after `property`, added to the last element declared.
fn add_property(elements: &mut [Element], words: &[&str], line: &str) -> Result<(), PlyError> {
    let property = match words {
        ["list", ct, vt, _name] => match (Scalar::parse(ct), Scalar::parse(vt)) {
            (Some(ct), Some(_)) => Property::List(ct),
            _ => {
                let line = line.trim();
                return Err(PlyError::BadHeader(format!("bad list types in `{line}`")));
            }
        },
        [ty, name] => {
            let ty = Scalar::parse(ty)
                .ok_or_else(|| PlyError::BadHeader(format!("unknown type `{ty}`")))?;
            Property::Scalar(name.to_string(), ty)
        }
        _ => {
            let line = line.trim();
            return Err(PlyError::BadHeader(format!("unexpected line `{line}`")));
        }
    };
    elements
        .last_mut()
        .ok_or_else(|| PlyError::BadHeader("property before element".into()))?
        .props
        .push(property);
    Ok(())
}

/// The indices of the vertex element's x, y and z properties; a vertex with a list property
/// is refused (its size would vary).
fn xyz_of(vertex: &Element) -> Result<[usize; 3], PlyError> {
    let find = |n: &str| {
        vertex
            .props
            .iter()
            .position(|p| matches!(p, Property::Scalar(name, _) if name == n))
    };
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        return Err(PlyError::NoXyz);
    };
    if vertex.props.iter().any(|p| matches!(p, Property::List(..))) {
        return Err(PlyError::BadHeader(
            "list property in the vertex element".into(),
        ));
    }
    Ok([ix, iy, iz])
}

/// Room for the header's claimed count of points: at most 64k, the rest as they arrive.
fn points_for(vertex: &Element) -> Vec<Point3<f32>> {
    Vec::with_capacity(vertex.count.min(1 << 16))
}

/// The vertices of a binary body, after skipping the (fixed-size) elements `before` them.
fn read_binary_vertices(
    r: &mut impl Read,
    before: &[Element],
    vertex: &Element,
    [ix, iy, iz]: [usize; 3],
) -> Result<Vec<Point3<f32>>, PlyError> {
    for e in before {
        skip_binary_element(r, e)?;
    }
    let mut at = 0;
    let offsets: Vec<(usize, Scalar)> = vertex
        .props
        .iter()
        .map(|p| {
            let t = match p {
                Property::Scalar(_, t) => *t,
                Property::List(ct) => *ct,
            };
            at += t.size();
            (at - t.size(), t)
        })
        .collect();
    let mut buf = vec![0u8; at];
    let mut points = points_for(vertex);
    for i in 0..vertex.count {
        r.read_exact(&mut buf)
            .map_err(|_| PlyError::Truncated(format!("vertex {i} of {}", vertex.count)))?;
        let v = |idx: usize| {
            let (o, t) = offsets[idx];
            t.read_le(&buf[o..]) as f32
        };
        points.push(Point3::new(v(ix), v(iy), v(iz)));
    }
    Ok(points)
}

/// Skips element `e` of a binary body, as one byte count, not element by element: an element
/// without properties and a huge count would otherwise loop on empty reads for as long as it
/// says.
fn skip_binary_element(r: &mut impl Read, e: &Element) -> Result<(), PlyError> {
    let mut size = 0usize;
    for p in &e.props {
        match p {
            Property::Scalar(_, t) => size += t.size(),
            Property::List(..) => {
                return Err(PlyError::BadHeader(format!(
                    "list property in element `{}` before vertex",
                    e.name
                )))
            }
        }
    }
    let bytes = (size as u64)
        .checked_mul(e.count as u64)
        .ok_or_else(|| PlyError::BadHeader(format!("element `{}` is too large", e.name)))?;
    let skipped = std::io::copy(&mut r.take(bytes), &mut std::io::sink())?;
    if skipped < bytes {
        return Err(PlyError::Truncated(format!("element `{}`", e.name)));
    }
    Ok(())
}

/// The vertices of an ASCII body, after skipping the lines of the elements `before` them.
fn read_ascii_vertices(
    r: impl BufRead,
    before: &[Element],
    vertex: &Element,
    [ix, iy, iz]: [usize; 3],
) -> Result<Vec<Point3<f32>>, PlyError> {
    let mut lines = r.lines();
    for e in before {
        for _ in 0..e.count {
            lines
                .next()
                .ok_or_else(|| PlyError::Truncated(format!("element `{}`", e.name)))??;
        }
    }
    let mut points = points_for(vertex);
    for i in 0..vertex.count {
        let l = lines
            .next()
            .ok_or_else(|| PlyError::Truncated(format!("vertex {i} of {}", vertex.count)))??;
        let words: Vec<&str> = l.split_whitespace().collect();
        let v = |idx: usize| -> Result<f32, PlyError> {
            let w = words
                .get(idx)
                .ok_or_else(|| PlyError::Truncated(format!("vertex {i} has too few values")))?;
            w.parse::<f32>()
                .map_err(|_| PlyError::BadValue(format!("`{w}` in vertex {i}")))
        };
        points.push(Point3::new(v(ix)?, v(iy)?, v(iz)?));
    }
    Ok(points)
}

/// Writes a cloud as binary little-endian PLY with float x, y, z and a `comment origin` line.
pub fn write_cloud(
    mut w: impl Write,
    points: &[Point3<f32>],
    origin: Option<&Point3<f64>>,
) -> std::io::Result<()> {
    let mut out = Vec::with_capacity(200 + points.len() * 12);
    out.extend_from_slice(b"ply\nformat binary_little_endian 1.0\n");
    if let Some(o) = origin {
        out.extend_from_slice(format!("comment origin {} {} {}\n", o.x, o.y, o.z).as_bytes());
    }
    out.extend_from_slice(
        format!(
            "element vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
            points.len()
        )
        .as_bytes(),
    );
    for p in points {
        for c in [p.x, p.y, p.z] {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    w.write_all(&out)
}

impl RoiMap {
    /// Writes every known voxel as binary little-endian PLY: float `x`, `y`, `z` (voxel centre),
    /// float `occupancy` and `roi` (log-odds). Voxels sorted by key.
    pub fn write_ply(&self, mut w: impl Write) -> std::io::Result<()> {
        let mut voxels: Vec<_> = self.iter().collect();
        voxels.sort_unstable_by_key(|(k, _)| *k);
        let mut out = Vec::with_capacity(300 + voxels.len() * 20);
        out.extend_from_slice(
            format!(
                "ply\nformat binary_little_endian 1.0\ncomment glasshouse roimap, resolution {} m\n\
                 element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
                 property float occupancy\nproperty float roi\nend_header\n",
                self.config.resolution_m,
                voxels.len()
            )
            .as_bytes(),
        );
        for (k, v) in voxels {
            let c = self.centre_of(k);
            for f in [
                c.x as f32,
                c.y as f32,
                c.z as f32,
                v.occupancy_logodds,
                v.roi_logodds,
            ] {
                out.extend_from_slice(&f.to_le_bytes());
            }
        }
        w.write_all(&out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const XYZ: &str = "property float x\nproperty float y\nproperty float z\n";

    fn binary(elements_before: &str, vertices: usize, data: &[u8]) -> Vec<u8> {
        let mut file = format!(
            "ply\nformat binary_little_endian 1.0\n{elements_before}element vertex {vertices}\n{XYZ}end_header\n"
        )
        .into_bytes();
        file.extend_from_slice(data);
        file
    }

    #[test]
    fn an_element_without_properties_and_a_huge_count_is_skipped_at_once() {
        let point: Vec<u8> = [1.0f32, 2.0, 3.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let file = binary(&format!("element empty {}\n", u64::MAX), 1, &point);
        let cloud = read_cloud(file.as_slice()).expect("reads");
        assert_eq!(cloud.points, vec![Point3::new(1.0, 2.0, 3.0)]);
    }

    #[test]
    fn elements_larger_than_the_file_are_errors() {
        let file = binary("element face 1000\nproperty int a\n", 1, &[0; 12]);
        assert!(matches!(
            read_cloud(file.as_slice()),
            Err(PlyError::Truncated(_))
        ));
        let huge = format!("element face {}\nproperty double a\n", u64::MAX);
        assert!(matches!(
            read_cloud(binary(&huge, 1, &[0; 12]).as_slice()),
            Err(PlyError::BadHeader(_))
        ));
        let many = binary("", usize::MAX, &[0; 12]);
        assert!(matches!(
            read_cloud(many.as_slice()),
            Err(PlyError::Truncated(_))
        ));
    }
}
