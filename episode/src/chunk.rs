//! The records of one MCAP chunk, read without trusting its lengths. mcap 0.26's `ChunkReader`
//! takes each record's length from the decompressed bytes and allocates it before anything
//! is checked, so one flipped byte in a chunk (a zstd raw literal) aborts the whole process
//! ("memory allocation of 8676466157105982985 bytes failed"). Here mcap's sans-io reader
//! reads the chunk with every length bounded by the chunk's own size (at most
//! [`MAX_CHUNK_BYTES`]) and, when the chunk has a CRC, checks it before any record is given.

use mcap::records::{ChunkHeader, Record, op};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use mcap::{McapError, McapResult};

/// The largest chunk read, uncompressed (the recorder's hold a second of the rig each).
pub const MAX_CHUNK_BYTES: u64 = 1 << 30;

/// The records of the chunk `header` + `compressed` (as `mcap::read::LinearReader` gives it),
/// all or none.
pub(crate) fn chunk_records(header: &ChunkHeader, compressed: &[u8]) -> McapResult<Vec<Record<'static>>> {
    if header.uncompressed_size > MAX_CHUNK_BYTES {
        return Err(McapError::ChunkTooLarge(header.uncompressed_size));
    }
    // The chunk record again, as the file had it, for the sans-io reader (no magic).
    let name = header.compression.as_bytes();
    let mut stream = vec![op::CHUNK];
    let body_len = 8 + 8 + 8 + 4 + 4 + name.len() + 8 + compressed.len();
    stream.extend((body_len as u64).to_le_bytes());
    stream.extend(header.message_start_time.to_le_bytes());
    stream.extend(header.message_end_time.to_le_bytes());
    stream.extend(header.uncompressed_size.to_le_bytes());
    stream.extend(header.uncompressed_crc.to_le_bytes());
    stream.extend((name.len() as u32).to_le_bytes());
    stream.extend(name);
    stream.extend((compressed.len() as u64).to_le_bytes());
    stream.extend(compressed);
    let checked = header.uncompressed_crc != 0;
    let limit = (header.uncompressed_size as usize).max(body_len);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_validate_chunk_crcs(checked)
            .with_prevalidate_chunk_crcs(checked)
            .with_record_length_limit(limit),
    );
    let mut rest: &[u8] = &stream;
    let mut records = Vec::new();
    while let Some(event) = reader.next_event() {
        match event? {
            LinearReadEvent::ReadRequest(need) => {
                let n = need.min(rest.len());
                reader.insert(n).copy_from_slice(&rest[..n]);
                reader.notify_read(n);
                rest = &rest[n..];
            }
            LinearReadEvent::Record { data, opcode } => records.push(mcap::parse_record(opcode, data)?.into_owned()),
        }
    }
    Ok(records)
}

/// Every record of the MCAP file in `buf`, in file order, each chunk opened into its records
/// with [`chunk_records`]'s bounds (so a foreign or damaged file is an error, never an
/// allocation it claims). The first error ends the walk and is returned; the records before
/// it have been given.
pub fn walk_records(buf: &[u8], mut on_record: impl FnMut(Record<'_>)) -> McapResult<()> {
    let reader = mcap::read::LinearReader::new_with_options(buf, mcap::read::Options::IgnoreEndMagic.into())?;
    for rec in reader {
        match rec? {
            Record::Chunk { header, data } => chunk_records(&header, &data)?.into_iter().for_each(&mut on_record),
            r => on_record(r),
        }
    }
    Ok(())
}
