//! The `ARROW:schema` entry of a parquet file's metadata: the Arrow schema of its columns, as
//! Arrow writers store it so that a reader restores the Arrow types the file was written with.
//! LeRobot's data files hold vectors as `fixed_size_list<element: float>[N]` (Hugging Face
//! `datasets` writes `Sequence(length=N)` that way); the parquet schema alone says only "list",
//! so without this entry pyarrow reads them back as variable `list<float>`.
//!
//! The value is base64 of an Arrow IPC message: the continuation marker `0xFFFFFFFF`, the
//! flatbuffer's length (padded to 8 bytes), then a `Message` flatbuffer holding the `Schema`
//! (format/Message.fbs and format/Schema.fbs of the Arrow project). Only the few types the
//! recorder writes are encoded.

use base64::Engine;
use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

/// An Arrow type the recorder writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ArrowType {
    /// 32-bit float.
    Float32,
    /// 64-bit signed integer.
    Int64,
    /// `fixed_size_list<element: float>[n]`.
    Float32List(i32),
}

// Type union tags (Schema.fbs `union Type`).
const TYPE_INT: u8 = 2;
const TYPE_FLOATING_POINT: u8 = 3;
const TYPE_FIXED_SIZE_LIST: u8 = 16;
// `enum Precision`: SINGLE.
const PRECISION_SINGLE: i16 = 1;
// `enum MetadataVersion`: V5; `union MessageHeader`: Schema.
const METADATA_V5: i16 = 4;
const HEADER_SCHEMA: u8 = 1;

/// The vtable offset of a table's field number `id`.
const fn slot(id: u16) -> u16 {
    4 + 2 * id
}

fn type_table(fbb: &mut FlatBufferBuilder, t: ArrowType) -> (u8, WIPOffset<UnionWIPOffset>) {
    match t {
        ArrowType::Float32 => {
            let start = fbb.start_table();
            fbb.push_slot::<i16>(slot(0), PRECISION_SINGLE, 0);
            (TYPE_FLOATING_POINT, fbb.end_table(start).as_union_value())
        }
        ArrowType::Int64 => {
            let start = fbb.start_table();
            fbb.push_slot::<i32>(slot(0), 64, 0);
            fbb.push_slot::<bool>(slot(1), true, false);
            (TYPE_INT, fbb.end_table(start).as_union_value())
        }
        ArrowType::Float32List(n) => {
            let start = fbb.start_table();
            fbb.push_slot::<i32>(slot(0), n, 0);
            (TYPE_FIXED_SIZE_LIST, fbb.end_table(start).as_union_value())
        }
    }
}

/// A nullable `Field` table (Schema.fbs: name 0, nullable 1, type_type 2, type 3,
/// dictionary 4, children 5).
fn field<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    name: &str,
    t: ArrowType,
) -> WIPOffset<flatbuffers::TableFinishedWIPOffset> {
    let children = match t {
        ArrowType::Float32List(_) => {
            let element = field(fbb, "element", ArrowType::Float32);
            Some(fbb.create_vector(&[element]))
        }
        _ => None,
    };
    let children = children.unwrap_or_else(|| {
        fbb.create_vector::<WIPOffset<flatbuffers::TableFinishedWIPOffset>>(&[])
    });
    let name = fbb.create_string(name);
    let (tag, table) = type_table(fbb, t);
    let start = fbb.start_table();
    fbb.push_slot_always(slot(0), name);
    fbb.push_slot::<bool>(slot(1), true, false);
    fbb.push_slot::<u8>(slot(2), tag, 0);
    fbb.push_slot_always(slot(3), table);
    fbb.push_slot_always(slot(5), children);
    fbb.end_table(start)
}

/// The `ARROW:schema` value for columns `(name, type)` in order.
pub fn arrow_schema(columns: &[(&str, ArrowType)]) -> String {
    let mut fbb = FlatBufferBuilder::new();
    let fields: Vec<_> = columns
        .iter()
        .map(|&(name, t)| field(&mut fbb, name, t))
        .collect();
    let fields = fbb.create_vector(&fields);
    // Schema.fbs `table Schema`: endianness 0 (Little, the default), fields 1.
    let start = fbb.start_table();
    fbb.push_slot_always(slot(1), fields);
    let schema = fbb.end_table(start);
    // Message.fbs `table Message`: version 0, header_type 1, header 2, bodyLength 3.
    let start = fbb.start_table();
    fbb.push_slot::<i16>(slot(0), METADATA_V5, 0);
    fbb.push_slot::<u8>(slot(1), HEADER_SCHEMA, 0);
    fbb.push_slot_always(slot(2), schema);
    fbb.push_slot::<i64>(slot(3), 0, 0);
    let message = fbb.end_table(start);
    fbb.finish_minimal(message);
    let body = fbb.finished_data();
    let padded = body.len().div_ceil(8) * 8;
    let mut out = Vec::with_capacity(8 + padded);
    out.extend_from_slice(&0xFFFF_FFFFu32.to_le_bytes());
    out.extend_from_slice(&(padded as i32).to_le_bytes());
    out.extend_from_slice(body);
    out.resize(8 + padded, 0);
    base64::engine::general_purpose::STANDARD.encode(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_message_is_an_encapsulated_flatbuffer_naming_every_column() {
        let text = arrow_schema(&[
            ("observation.state", ArrowType::Float32List(16)),
            ("timestamp", ArrowType::Float32),
            ("index", ArrowType::Int64),
        ]);
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(text)
            .unwrap();
        assert_eq!(&bytes[..4], &[0xFF; 4], "continuation marker");
        let len = i32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]) as usize;
        assert_eq!(len % 8, 0);
        assert_eq!(bytes.len(), 8 + len);
        let body = &bytes[8..];
        for name in ["observation.state", "element", "timestamp", "index"] {
            assert!(
                body.windows(name.len()).any(|w| w == name.as_bytes()),
                "{name}"
            );
        }
        // The root offset points inside the buffer, at a table whose vtable is inside too.
        let root = u32::from_le_bytes([body[0], body[1], body[2], body[3]]) as usize;
        assert!(root + 4 <= body.len());
        let vtable = root as i64
            - i64::from(i32::from_le_bytes([
                body[root],
                body[root + 1],
                body[root + 2],
                body[root + 3],
            ]));
        assert!(vtable >= 0 && (vtable as usize) < body.len());
    }
}
