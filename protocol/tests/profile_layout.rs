//! The board's flash record of a [`RigProfile`] is keyed on
//! [`RigProfile::LAYOUT`], and this test ties that key to the struct. It walks the profile's own
//! `Serialize` impl with a serializer that writes the *shape* (struct and field names, primitive
//! types, enum names with every variant's name and wire index, in order) instead of the values,
//! and requires the CRC-32 of that shape to be the constant. Any field added, removed, renamed,
//! reordered or retyped, and any enum variant added, removed, renamed or reordered (postcard
//! writes a variant as its index, so a reorder would silently turn a stored `ExternalDac16` into
//! `InternalDac12`) changes the shape: the test fails and names the new key, so the layout change
//! and the new key go in together, and a board never decodes an old record's bytes with a new
//! layout (it reads "no profile stored" instead).

use std::fmt::Write as _;

use serde::ser::{self, Serialize};
use subsurf_protocol::RigProfile;

#[derive(Debug)]
struct Unsupported(String);

impl std::fmt::Display for Unsupported {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "shape serializer: {}", self.0)
    }
}

impl std::error::Error for Unsupported {}

impl ser::Error for Unsupported {
    fn custom<T: std::fmt::Display>(msg: T) -> Self {
        Self(msg.to_string())
    }
}

/// Writes a value's shape: `Name{field:type,...}`, `u16`, `bool`, `Enum[0=A,1=B]` (a unit
/// variant writes its enum's whole variant list, [`variants`], so the shape does not depend on
/// the values).
#[derive(Default)]
struct Shape(String);

/// Every variant of each enum the profile holds, as its `Serialize` impl writes them (name and
/// index). The exhaustive `match` makes a new variant a compile error here, so the list cannot
/// fall behind the enum; an enum not listed fails the test.
fn variants(enum_name: &str) -> Result<String, Unsupported> {
    use subsurf_protocol::GalvoOutput;
    let all: Vec<Box<dyn erased::Variant>> = match enum_name {
        "GalvoOutput" => {
            let list = [GalvoOutput::ExternalDac16, GalvoOutput::InternalDac12];
            for v in list {
                match v {
                    GalvoOutput::ExternalDac16 | GalvoOutput::InternalDac12 => {}
                }
            }
            list.into_iter()
                .map(|v| Box::new(v) as Box<dyn erased::Variant>)
                .collect()
        }
        other => {
            return Err(Unsupported(format!(
                "enum {other}: list its variants in `variants` (profile_layout.rs)"
            )));
        }
    };
    let mut out = String::new();
    for v in all {
        let (index, name) = v.index_and_name()?;
        write!(out, "{index}={name},").map_err(ser::Error::custom)?;
    }
    Ok(out)
}

/// A unit variant's wire index and name, through its own `Serialize` impl.
mod erased {
    use super::*;

    pub trait Variant {
        fn index_and_name(&self) -> Result<(u32, &'static str), Unsupported>;
    }

    impl<T: Serialize> Variant for T {
        fn index_and_name(&self) -> Result<(u32, &'static str), Unsupported> {
            let mut capture = Capture(None);
            self.serialize(&mut capture)?;
            capture
                .0
                .ok_or_else(|| Unsupported("not a unit variant".into()))
        }
    }

    struct Capture(Option<(u32, &'static str)>);

    macro_rules! refuse {
        ($($f:ident($($a:ty),*) -> $r:ty),*) => {$(
            fn $f(self, $(_: $a),*) -> Result<$r, Unsupported> {
                Err(Unsupported(stringify!($f).into()))
            }
        )*};
    }

    impl ser::Serializer for &mut Capture {
        type Ok = ();
        type Error = Unsupported;
        type SerializeSeq = ser::Impossible<(), Unsupported>;
        type SerializeTuple = ser::Impossible<(), Unsupported>;
        type SerializeTupleStruct = ser::Impossible<(), Unsupported>;
        type SerializeTupleVariant = ser::Impossible<(), Unsupported>;
        type SerializeMap = ser::Impossible<(), Unsupported>;
        type SerializeStruct = ser::Impossible<(), Unsupported>;
        type SerializeStructVariant = ser::Impossible<(), Unsupported>;

        fn serialize_unit_variant(
            self,
            _: &'static str,
            index: u32,
            variant: &'static str,
        ) -> Result<(), Unsupported> {
            self.0 = Some((index, variant));
            Ok(())
        }

        fn serialize_some<T: ?Sized + Serialize>(self, _: &T) -> Result<(), Unsupported> {
            Err(Unsupported("serialize_some".into()))
        }
        fn serialize_newtype_struct<T: ?Sized + Serialize>(
            self,
            _: &'static str,
            _: &T,
        ) -> Result<(), Unsupported> {
            Err(Unsupported("serialize_newtype_struct".into()))
        }
        fn serialize_newtype_variant<T: ?Sized + Serialize>(
            self,
            _: &'static str,
            _: u32,
            _: &'static str,
            _: &T,
        ) -> Result<(), Unsupported> {
            Err(Unsupported("serialize_newtype_variant".into()))
        }

        refuse!(
            serialize_bool(bool) -> (), serialize_i8(i8) -> (), serialize_i16(i16) -> (),
            serialize_i32(i32) -> (), serialize_i64(i64) -> (), serialize_u8(u8) -> (),
            serialize_u16(u16) -> (), serialize_u32(u32) -> (), serialize_u64(u64) -> (),
            serialize_f32(f32) -> (), serialize_f64(f64) -> (), serialize_char(char) -> (),
            serialize_str(&str) -> (), serialize_bytes(&[u8]) -> (), serialize_none() -> (),
            serialize_unit() -> (), serialize_unit_struct(&'static str) -> (),
            serialize_seq(Option<usize>) -> Self::SerializeSeq,
            serialize_tuple(usize) -> Self::SerializeTuple,
            serialize_tuple_struct(&'static str, usize) -> Self::SerializeTupleStruct,
            serialize_tuple_variant(&'static str, u32, &'static str, usize) -> Self::SerializeTupleVariant,
            serialize_map(Option<usize>) -> Self::SerializeMap,
            serialize_struct(&'static str, usize) -> Self::SerializeStruct,
            serialize_struct_variant(&'static str, u32, &'static str, usize) -> Self::SerializeStructVariant
        );
    }
}

macro_rules! primitive {
    ($($f:ident: $t:ty => $name:literal),*) => {$(
        fn $f(self, _: $t) -> Result<(), Unsupported> {
            self.0.push_str($name);
            Ok(())
        }
    )*};
}

macro_rules! unsupported {
    ($($f:ident($($a:ty),*) -> $r:ty),*) => {$(
        fn $f(self, $(_: $a),*) -> Result<$r, Unsupported> {
            Err(Unsupported(format!("{} (extend the shape serializer)", stringify!($f))))
        }
    )*};
}

impl ser::Serializer for &mut Shape {
    type Ok = ();
    type Error = Unsupported;
    type SerializeSeq = ser::Impossible<(), Unsupported>;
    type SerializeTuple = ser::Impossible<(), Unsupported>;
    type SerializeTupleStruct = ser::Impossible<(), Unsupported>;
    type SerializeTupleVariant = ser::Impossible<(), Unsupported>;
    type SerializeMap = ser::Impossible<(), Unsupported>;
    type SerializeStruct = Self;
    type SerializeStructVariant = ser::Impossible<(), Unsupported>;

    primitive!(
        serialize_bool: bool => "bool",
        serialize_i8: i8 => "i8", serialize_i16: i16 => "i16", serialize_i32: i32 => "i32",
        serialize_i64: i64 => "i64", serialize_u8: u8 => "u8", serialize_u16: u16 => "u16",
        serialize_u32: u32 => "u32", serialize_u64: u64 => "u64", serialize_f32: f32 => "f32",
        serialize_f64: f64 => "f64", serialize_char: char => "char"
    );
    unsupported!(
        serialize_str(&str) -> (),
        serialize_bytes(&[u8]) -> (),
        serialize_none() -> (),
        serialize_unit() -> (),
        serialize_unit_struct(&'static str) -> (),
        serialize_seq(Option<usize>) -> Self::SerializeSeq,
        serialize_tuple(usize) -> Self::SerializeTuple,
        serialize_tuple_struct(&'static str, usize) -> Self::SerializeTupleStruct,
        serialize_tuple_variant(&'static str, u32, &'static str, usize) -> Self::SerializeTupleVariant,
        serialize_map(Option<usize>) -> Self::SerializeMap,
        serialize_struct_variant(&'static str, u32, &'static str, usize) -> Self::SerializeStructVariant
    );

    fn serialize_some<T: ?Sized + Serialize>(self, _: &T) -> Result<(), Unsupported> {
        Err(Unsupported("Option (extend the shape serializer)".into()))
    }

    fn serialize_unit_variant(
        self,
        name: &'static str,
        _: u32,
        _: &'static str,
    ) -> Result<(), Unsupported> {
        let list = variants(name)?;
        write!(self.0, "{name}[{list}]").map_err(ser::Error::custom)?;
        Ok(())
    }

    fn serialize_newtype_struct<T: ?Sized + Serialize>(
        self,
        name: &'static str,
        value: &T,
    ) -> Result<(), Unsupported> {
        write!(self.0, "{name}(").map_err(ser::Error::custom)?;
        value.serialize(&mut *self)?;
        self.0.push(')');
        Ok(())
    }

    fn serialize_newtype_variant<T: ?Sized + Serialize>(
        self,
        name: &'static str,
        _: u32,
        _: &'static str,
        _: &T,
    ) -> Result<(), Unsupported> {
        Err(Unsupported(format!(
            "data-carrying variant of {name} (extend the shape serializer)"
        )))
    }

    fn serialize_struct(self, name: &'static str, _: usize) -> Result<Self, Unsupported> {
        write!(self.0, "{name}{{").map_err(ser::Error::custom)?;
        Ok(self)
    }
}

impl ser::SerializeStruct for &mut Shape {
    type Ok = ();
    type Error = Unsupported;

    fn serialize_field<T: ?Sized + Serialize>(
        &mut self,
        key: &'static str,
        value: &T,
    ) -> Result<(), Unsupported> {
        write!(self.0, "{key}:").map_err(ser::Error::custom)?;
        value.serialize(&mut **self)?;
        self.0.push(',');
        Ok(())
    }

    fn end(self) -> Result<(), Unsupported> {
        self.0.push('}');
        Ok(())
    }
}

fn shape(profile: &RigProfile) -> String {
    let mut s = Shape::default();
    profile.serialize(&mut s).expect("the profile's shape");
    s.0
}

#[test]
fn the_layout_key_is_the_crc_of_the_profile_s_shape() {
    let shape = shape(&RigProfile::DEFAULT);
    let crc = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(shape.as_bytes());
    assert_eq!(
        RigProfile::LAYOUT,
        crc,
        "RigProfile's layout changed; set RigProfile::LAYOUT = {crc:#010x} (stored profiles of \
         the old layout then read as none stored). Shape: {shape}"
    );
}

#[test]
fn the_shape_does_not_depend_on_the_values() {
    let mut other = RigProfile::DEFAULT;
    other.laser.active_low = !other.laser.active_low;
    other.motor.microsteps = 7;
    other.galvo.output = match other.galvo.output {
        subsurf_protocol::GalvoOutput::ExternalDac16 => {
            subsurf_protocol::GalvoOutput::InternalDac12
        }
        _ => subsurf_protocol::GalvoOutput::ExternalDac16,
    };
    assert_eq!(shape(&other), shape(&RigProfile::DEFAULT));
    assert!(shape(&other).contains("LaserProfile{channels:u8,active_low:bool,"));
}

/// The variants are in the shape with their wire indices: reordering `GalvoOutput` (which
/// postcard writes as an index) gives another key.
#[test]
fn the_shape_names_every_variant_with_its_index() {
    let shape = shape(&RigProfile::DEFAULT);
    assert!(
        shape.contains("output:GalvoOutput[0=ExternalDac16,1=InternalDac12,]"),
        "{shape}"
    );
    let swapped = shape.replace(
        "[0=ExternalDac16,1=InternalDac12,]",
        "[0=InternalDac12,1=ExternalDac16,]",
    );
    let crc = |s: &str| crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(s.as_bytes());
    assert_ne!(crc(&shape), crc(&swapped));
}
