//! The exported mesh as binary glTF 2.0 (`.glb`, through the `gltf` crate's JSON types and GLB
//! container): positions and normals in metres (glTF's unit), triangle indices, `COLOR_0` (the
//! subsurface colour times alpha, clamped to [0, 1], for viewers that know nothing else), and the
//! converted parameters as glTF's application-specific attributes (names starting with `_`,
//! kept by readers that keep custom attributes):
//!
//! | attribute | type | meaning |
//! | --- | --- | --- |
//! | `_SUBSURFACE_COLOR` | VEC3 float | total diffuse reflectance per channel (Cycles' Subsurface Color) |
//! | `_SUBSURFACE_RADIUS` | VEC3 float | Cycles' Subsurface Radius per channel, metres |
//! | `_ALPHA` | VEC3 float | alpha(x_o), Eq. 2/6 (the lattice's where the mesh was refined) |
//! | `_CONVERSION_LOG_E` | VEC3 float | log E of the conversion per channel, −1 where none |
//!
//! Blender 3.4's glTF importer drops `_` attributes, so the export's build script reads them from
//! this file itself (`build_blend.py`).

use std::collections::BTreeMap;

use gltf::json::{self, validation::Checked::Valid, validation::USize64};

use super::ExportError;
use super::mesh::ExportMesh;

/// Attribute names, as written (the `_` prefix is glTF's mark of an application attribute).
pub const ATTRIBUTES: [(&str, &str); 4] = [
    ("_SUBSURFACE_COLOR", "subsurface colour"),
    ("_SUBSURFACE_RADIUS", "subsurface radius, m"),
    ("_ALPHA", "alpha"),
    ("_CONVERSION_LOG_E", "conversion log E"),
];

/// The second lobe's attributes, written only with two lobes ([`super::ColourRule::TwoLobe`]).
pub const SLOW_ATTRIBUTES: [(&str, &str); 3] = [
    ("_SUBSURFACE_COLOR_SLOW", "slow lobe's subsurface colour"),
    (
        "_SUBSURFACE_RADIUS_SLOW",
        "slow lobe's subsurface radius, m",
    ),
    ("_LOBE_MIX", "Mix Shader factor: the slow lobe's share"),
];

/// The `.glb` bytes of `mesh`, lengths scaled by `metres_per_unit` (the model is in mm: 0.001).
pub fn glb_bytes(
    mesh: &ExportMesh,
    metres_per_unit: f64,
    generator: &str,
) -> Result<Vec<u8>, ExportError> {
    let n = mesh.positions.len();
    let bad = |m: String| ExportError::Invalid(m);
    if n == 0 || mesh.triangles.is_empty() {
        return Err(bad("the mesh has no vertices or no triangles".into()));
    }
    if n > u32::MAX as usize {
        return Err(bad(format!("{n} vertices exceed glTF's 32-bit indices")));
    }
    for (what, len) in [
        ("normals", mesh.normals.len()),
        ("colour", mesh.colour.len()),
        ("radius", mesh.radius_mm.len()),
        ("alpha", mesh.alpha.len()),
        ("log E", mesh.log_e.len()),
    ] {
        if len != n {
            return Err(bad(format!("{what}: {len} entries for {n} vertices")));
        }
    }
    for (what, len) in [
        ("slow colour", mesh.slow_colour.len()),
        ("slow radius", mesh.slow_radius_mm.len()),
        ("lobe mix", mesh.slow_weight.len()),
    ] {
        if len != 0 && len != n {
            return Err(bad(format!("{what}: {len} entries for {n} vertices")));
        }
    }
    if let Some(t) = mesh
        .triangles
        .iter()
        .find(|t| t.iter().any(|&v| v as usize >= n))
    {
        return Err(bad(format!("triangle {t:?} refers to a missing vertex")));
    }
    let s = metres_per_unit;
    let to_f32 = |v: f64, what: &str| -> Result<f32, ExportError> {
        let x = v as f32;
        if x.is_finite() {
            Ok(x)
        } else {
            Err(bad(format!("{what} {v} is not a finite 32-bit float")))
        }
    };
    let vec3 = |data: &[[f64; 3]], scale: f64, what: &str| -> Result<Vec<[f32; 3]>, ExportError> {
        data.iter()
            .map(|p| {
                Ok([
                    to_f32(p[0] * scale, what)?,
                    to_f32(p[1] * scale, what)?,
                    to_f32(p[2] * scale, what)?,
                ])
            })
            .collect()
    };
    let positions = vec3(&mesh.positions, s, "position")?;
    let normals = vec3(&mesh.normals, 1.0, "normal")?;
    let colour = vec3(&mesh.colour, 1.0, "subsurface colour")?;
    let radius = vec3(&mesh.radius_mm, s, "subsurface radius")?;
    let alpha = vec3(&mesh.alpha, 1.0, "alpha")?;
    let log_e: Vec<[f32; 3]> = mesh
        .log_e
        .iter()
        .map(|l| l.map(|x| if x.is_finite() { x as f32 } else { -1.0 }))
        .collect();
    let slow_colour = vec3(&mesh.slow_colour, 1.0, "slow subsurface colour")?;
    let slow_radius = vec3(&mesh.slow_radius_mm, s, "slow subsurface radius")?;
    let slow_weight = vec3(&mesh.slow_weight, 1.0, "lobe mix")?;
    let two = !slow_weight.is_empty();
    // The preview: the light both lobes scatter, times alpha.
    let preview: Vec<[f32; 3]> = (0..n)
        .map(|v| {
            let (c, a) = (colour[v], alpha[v]);
            [0, 1, 2].map(|k| {
                let total = if two {
                    let w = slow_weight[v][k];
                    c[k] * (1.0 - w) + slow_colour[v][k] * w
                } else {
                    c[k]
                };
                (total * a[k]).clamp(0.0, 1.0)
            })
        })
        .collect();

    let mut bin: Vec<u8> = Vec::new();
    let mut root = json::Root {
        asset: json::Asset {
            generator: Some(generator.to_string()),
            version: "2.0".into(),
            ..Default::default()
        },
        ..Default::default()
    };
    let buffer = root.push(json::Buffer {
        byte_length: USize64(0),
        name: None,
        uri: None,
        extensions: None,
        extras: Default::default(),
    });
    let mut view = |root: &mut json::Root, bytes: &[u8], target: json::buffer::Target| {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let offset = bin.len();
        bin.extend_from_slice(bytes);
        root.push(json::buffer::View {
            buffer,
            byte_length: USize64(bytes.len() as u64),
            byte_offset: Some(USize64(offset as u64)),
            byte_stride: None,
            name: None,
            target: Some(Valid(target)),
            extensions: None,
            extras: Default::default(),
        })
    };
    let mut vec3_accessor = |root: &mut json::Root,
                             data: &[[f32; 3]],
                             name: &str,
                             bounds: bool|
     -> json::Index<json::Accessor> {
        let bytes: Vec<u8> = data
            .iter()
            .flat_map(|p| p.iter().flat_map(|x| x.to_le_bytes()))
            .collect();
        let v = view(root, &bytes, json::buffer::Target::ArrayBuffer);
        let (min, max) = if bounds {
            let mut lo = [f32::INFINITY; 3];
            let mut hi = [f32::NEG_INFINITY; 3];
            for p in data {
                for k in 0..3 {
                    lo[k] = lo[k].min(p[k]);
                    hi[k] = hi[k].max(p[k]);
                }
            }
            (
                Some(json::Value::from(lo.to_vec())),
                Some(json::Value::from(hi.to_vec())),
            )
        } else {
            (None, None)
        };
        root.push(json::Accessor {
            buffer_view: Some(v),
            byte_offset: None,
            count: USize64(data.len() as u64),
            component_type: Valid(json::accessor::GenericComponentType(
                json::accessor::ComponentType::F32,
            )),
            extensions: None,
            extras: Default::default(),
            type_: Valid(json::accessor::Type::Vec3),
            min,
            max,
            name: Some(name.to_string()),
            normalized: false,
            sparse: None,
        })
    };
    let mut attributes = BTreeMap::new();
    use json::mesh::Semantic;
    attributes.insert(
        Valid(Semantic::Positions),
        vec3_accessor(&mut root, &positions, "POSITION", true),
    );
    attributes.insert(
        Valid(Semantic::Normals),
        vec3_accessor(&mut root, &normals, "NORMAL", false),
    );
    attributes.insert(
        Valid(Semantic::Colors(0)),
        vec3_accessor(&mut root, &preview, "COLOR_0", false),
    );
    for ((name, _), data) in ATTRIBUTES.iter().zip([&colour, &radius, &alpha, &log_e]) {
        attributes.insert(
            Valid(Semantic::Extras(name[1..].to_string())),
            vec3_accessor(&mut root, data, name, false),
        );
    }
    if two {
        for ((name, _), data) in
            SLOW_ATTRIBUTES
                .iter()
                .zip([&slow_colour, &slow_radius, &slow_weight])
        {
            attributes.insert(
                Valid(Semantic::Extras(name[1..].to_string())),
                vec3_accessor(&mut root, data, name, false),
            );
        }
    }
    let index_bytes: Vec<u8> = mesh
        .triangles
        .iter()
        .flat_map(|t| t.iter().flat_map(|i| i.to_le_bytes()))
        .collect();
    let iv = view(
        &mut root,
        &index_bytes,
        json::buffer::Target::ElementArrayBuffer,
    );
    let indices = root.push(json::Accessor {
        buffer_view: Some(iv),
        byte_offset: None,
        count: USize64(3 * mesh.triangles.len() as u64),
        component_type: Valid(json::accessor::GenericComponentType(
            json::accessor::ComponentType::U32,
        )),
        extensions: None,
        extras: Default::default(),
        type_: Valid(json::accessor::Type::Scalar),
        min: None,
        max: None,
        name: Some("indices".into()),
        normalized: false,
        sparse: None,
    });
    let m = root.push(json::Mesh {
        extensions: None,
        extras: Default::default(),
        name: Some("subsurf model".into()),
        primitives: vec![json::mesh::Primitive {
            attributes,
            extensions: None,
            extras: Default::default(),
            indices: Some(indices),
            material: None,
            mode: Valid(json::mesh::Mode::Triangles),
            targets: None,
        }],
        weights: None,
    });
    let node = root.push(json::Node {
        mesh: Some(m),
        name: Some("subsurf model".into()),
        ..Default::default()
    });
    let scene = root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        name: Some("subsurf export".into()),
        nodes: vec![node],
    });
    root.scene = Some(scene);
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    root.buffers[0].byte_length = USize64(bin.len() as u64);
    let json_bytes = root.to_vec().map_err(|e| bad(format!("glTF JSON: {e}")))?;
    let glb = gltf::binary::Glb {
        header: gltf::binary::Header {
            magic: *b"glTF",
            version: 2,
            // Filled in by `to_vec`.
            length: 0,
        },
        json: std::borrow::Cow::Owned(json_bytes),
        bin: Some(std::borrow::Cow::Owned(bin)),
    };
    glb.to_vec()
        .map_err(|e| bad(format!("writing the GLB container: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri() -> ExportMesh {
        ExportMesh {
            positions: vec![[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]],
            normals: vec![[0.0, 0.0, 1.0]; 3],
            triangles: vec![[0, 1, 2]],
            colour: vec![[0.5, 0.4, 0.3]; 3],
            radius_mm: vec![[2.0, 1.0, 0.5]; 3],
            alpha: vec![[1.0, 0.9, 1.1]; 3],
            log_e: vec![[0.01, f64::NAN, 0.02]; 3],
            ..Default::default()
        }
    }

    /// The gltf crate reads the file back (validated): metres, the custom attributes with
    /// their values, −1 for a missing log E.
    #[test]
    fn the_glb_reads_back_with_its_custom_attributes() {
        let bytes = glb_bytes(&tri(), 1e-3, "test").unwrap();
        let g = gltf::Gltf::from_slice(&bytes).unwrap();
        let bin = g.blob.as_deref().unwrap();
        let prim = g.meshes().next().unwrap().primitives().next().unwrap();
        let read = |sem: gltf::Semantic| -> Vec<[f32; 3]> {
            let r = prim.reader(|_| Some(bin));
            let acc = prim.get(&sem).unwrap();
            let view = acc.view().unwrap();
            let _ = r;
            let start = view.offset() + acc.offset();
            (0..acc.count())
                .map(|k| {
                    let at = |c: usize| {
                        let o = start + 12 * k + 4 * c;
                        f32::from_le_bytes(bin[o..o + 4].try_into().unwrap())
                    };
                    [at(0), at(1), at(2)]
                })
                .collect()
        };
        assert_eq!(read(gltf::Semantic::Positions)[1], [0.01, 0.0, 0.0]);
        assert_eq!(
            read(gltf::Semantic::Extras("SUBSURFACE_RADIUS".into()))[0],
            [0.002, 0.001, 0.0005]
        );
        assert_eq!(
            read(gltf::Semantic::Extras("CONVERSION_LOG_E".into()))[2],
            [0.01, -1.0, 0.02]
        );
        let preview = read(gltf::Semantic::Colors(0))[0];
        for (got, want) in preview.iter().zip([0.5, 0.36, 0.33]) {
            assert!((got - want).abs() < 1e-6, "{preview:?}");
        }
        let idx: Vec<u32> = prim
            .reader(|_| Some(bin))
            .read_indices()
            .unwrap()
            .into_u32()
            .collect();
        assert_eq!(idx, [0, 1, 2]);
        assert!(
            prim.get(&gltf::Semantic::Extras("LOBE_MIX".into()))
                .is_none()
        );

        // Two lobes: the slow lobe's attributes are there, and the preview is both lobes' light.
        let mut two = tri();
        two.slow_colour = vec![[1.0, 1.0, 1.0]; 3];
        two.slow_radius_mm = vec![[20.0, 10.0, 5.0]; 3];
        two.slow_weight = vec![[0.25; 3]; 3];
        let bytes = glb_bytes(&two, 1e-3, "test").unwrap();
        let g = gltf::Gltf::from_slice(&bytes).unwrap();
        let prim = g.meshes().next().unwrap().primitives().next().unwrap();
        for name in [
            "SUBSURFACE_COLOR_SLOW",
            "SUBSURFACE_RADIUS_SLOW",
            "LOBE_MIX",
        ] {
            assert!(
                prim.get(&gltf::Semantic::Extras(name.into())).is_some(),
                "{name}"
            );
        }
        two.slow_weight.pop();
        assert!(glb_bytes(&two, 1e-3, "t").is_err());
    }

    #[test]
    fn bad_meshes_are_refused() {
        let mut m = tri();
        m.triangles = vec![[0, 1, 7]];
        assert!(glb_bytes(&m, 1e-3, "t").is_err());
        let mut m = tri();
        m.colour[0][0] = f64::INFINITY;
        assert!(glb_bytes(&m, 1e-3, "t").is_err());
        let mut m = tri();
        m.alpha.pop();
        assert!(glb_bytes(&m, 1e-3, "t").is_err());
    }
}
