//! The representations of samples in WRITE_DATA and DATA (§7.7.1–7.7.2, §8.3.5.8, §8.3.5.10).
//!
//! `SampleData` is the user type's XCDR bytes with no length prefix, so in the sequence formats
//! (DATA_SEQ, SAMPLE_SEQ, PACKED_SAMPLES) consecutive samples can only be told apart by someone
//! who knows the type. [`decode_samples`] therefore takes an optional [`SampleSizer`]; without
//! one, a sequence of exactly one sample (which extends to the end) is still decoded, and a
//! longer one is refused with [`SampleError::NeedsType`].

use super::cdr::{CdrReader, CdrWriter};
use super::types::{data_format, Dialect};
use super::DecodeError;

/// `SampleInfoFlags` bits.
pub mod sample_state {
    /// The writer unregistered the instance.
    pub const INSTANCE_UNREGISTERED: u8 = 0x01;
    /// The instance was disposed.
    pub const INSTANCE_DISPOSED: u8 = 0x02;
    /// First sample of the instance the reader sees.
    pub const VIEW_NEW: u8 = 0x04;
    /// The sample was read before.
    pub const SAMPLE_READ: u8 = 0x08;
}

/// Most samples one WRITE_DATA or DATA may carry (a datagram holds fewer anyway).
pub const MAX_SAMPLES: usize = 65_536;

/// `SampleInfoDetail`: which of the sequence number and session time offset are present.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub enum SampleInfoDetail {
    /// Neither.
    #[default]
    Empty,
    /// The writer's or reader's sample sequence number.
    SequenceNumber(u32),
    /// Milliseconds since the session started.
    SessionTimeOffset(u32),
    /// Both.
    Both {
        /// Sample sequence number.
        sequence_number: u32,
        /// Milliseconds since the session started.
        session_time_offset: u32,
    },
}

/// Spec discriminators (`SampleInfoFormat`).
mod info_format {
    pub(super) const EMPTY: u8 = 0x00;
    pub(super) const SEQNUM: u8 = 0x01;
    pub(super) const TIMESTAMP: u8 = 0x02;
    pub(super) const SEQN_TIMS: u8 = 0x03;
}

impl SampleInfoDetail {
    /// The sequence number, if present.
    pub fn sequence_number(self) -> Option<u32> {
        match self {
            SampleInfoDetail::SequenceNumber(s)
            | SampleInfoDetail::Both {
                sequence_number: s, ..
            } => Some(s),
            _ => None,
        }
    }

    /// The session time offset in milliseconds, if present.
    pub fn session_time_offset(self) -> Option<u32> {
        match self {
            SampleInfoDetail::SessionTimeOffset(t)
            | SampleInfoDetail::Both {
                session_time_offset: t,
                ..
            } => Some(t),
            _ => None,
        }
    }

    fn from_parts(seq: Option<u32>, offset: Option<u32>) -> Self {
        match (seq, offset) {
            (None, None) => SampleInfoDetail::Empty,
            (Some(s), None) => SampleInfoDetail::SequenceNumber(s),
            (None, Some(t)) => SampleInfoDetail::SessionTimeOffset(t),
            (Some(s), Some(t)) => SampleInfoDetail::Both {
                sequence_number: s,
                session_time_offset: t,
            },
        }
    }
}

/// `SampleInfo` (Annex A form: state, then the detail union).
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct SampleInfo {
    /// [`sample_state`] bits; 0 = alive.
    pub state: u8,
    /// Sequence number and time offset.
    pub detail: SampleInfoDetail,
}

impl SampleInfo {
    /// Decodes a SampleInfo in `dialect`.
    pub fn decode(r: &mut CdrReader<'_>, dialect: Dialect) -> Result<Self, DecodeError> {
        let state = r.u8()?;
        let detail = match dialect {
            Dialect::Spec => match r.u8()? {
                info_format::EMPTY => SampleInfoDetail::Empty,
                info_format::SEQNUM => SampleInfoDetail::SequenceNumber(r.u32()?),
                info_format::TIMESTAMP => SampleInfoDetail::SessionTimeOffset(r.u32()?),
                info_format::SEQN_TIMS => SampleInfoDetail::Both {
                    sequence_number: r.u32()?,
                    session_time_offset: r.u32()?,
                },
                _ => return Err(DecodeError::InvalidValue("SampleInfoFormat")),
            },
            // eProsima: a u32 discriminator whose cases are shifted by one.
            Dialect::Eprosima => match r.u32()? {
                0 => SampleInfoDetail::SequenceNumber(r.u32()?),
                1 => SampleInfoDetail::SessionTimeOffset(r.u32()?),
                2 => SampleInfoDetail::Both {
                    sequence_number: r.u32()?,
                    session_time_offset: r.u32()?,
                },
                3 => SampleInfoDetail::Empty,
                _ => return Err(DecodeError::InvalidValue("SampleInfoFormat")),
            },
        };
        Ok(SampleInfo { state, detail })
    }

    /// Encodes in `dialect`.
    pub fn encode(&self, w: &mut CdrWriter<'_>, dialect: Dialect) {
        w.u8(self.state);
        let (spec, eprosima) = match self.detail {
            SampleInfoDetail::Empty => (info_format::EMPTY, 3),
            SampleInfoDetail::SequenceNumber(_) => (info_format::SEQNUM, 0),
            SampleInfoDetail::SessionTimeOffset(_) => (info_format::TIMESTAMP, 1),
            SampleInfoDetail::Both { .. } => (info_format::SEQN_TIMS, 2),
        };
        match dialect {
            Dialect::Spec => w.u8(spec),
            Dialect::Eprosima => w.u32(eprosima),
        }
        match self.detail {
            SampleInfoDetail::Empty => {}
            SampleInfoDetail::SequenceNumber(v) | SampleInfoDetail::SessionTimeOffset(v) => {
                w.u32(v)
            }
            SampleInfoDetail::Both {
                sequence_number,
                session_time_offset,
            } => {
                w.u32(sequence_number);
                w.u32(session_time_offset);
            }
        }
    }
}

/// `SampleInfoDelta` of a packed sample, relative to the `info_base`.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct SampleInfoDelta {
    /// The sample's own state bits.
    pub state: u8,
    /// Added to the base sequence number.
    pub seq_number_delta: u8,
    /// Added to the base time offset, in tenths of a second.
    pub timestamp_delta: u16,
}

impl SampleInfoDelta {
    /// The full SampleInfo of a packed sample: the base plus this delta (time in 100 ms units).
    pub fn apply(self, base: &SampleInfo) -> SampleInfo {
        let seq = base
            .detail
            .sequence_number()
            .map(|s| s.wrapping_add(u32::from(self.seq_number_delta)));
        let offset = base
            .detail
            .session_time_offset()
            .map(|t| t.wrapping_add(100 * u32::from(self.timestamp_delta)));
        SampleInfo {
            state: self.state,
            detail: SampleInfoDetail::from_parts(seq, offset),
        }
    }
}

/// One sample of a WRITE_DATA or DATA: its info (absent in the DATA formats) and its bytes.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct SampleRef<'a> {
    /// SampleInfo, for SAMPLE, SAMPLE_SEQ and PACKED_SAMPLES.
    pub info: Option<SampleInfo>,
    /// The serialized user data.
    pub data: &'a [u8],
}

/// Returns the serialized length of the sample at the start of the given bytes (which follow
/// the CDR stream at the given alignment offset), when the type is known.
pub type SampleSizer<'s> = &'s dyn Fn(&[u8], usize) -> Option<usize>;

/// Why a sample representation could not be decoded or encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum SampleError {
    /// Malformed bytes.
    #[error("malformed sample representation: {0}")]
    Decode(#[from] DecodeError),
    /// 0x04, 0x06 or 0x0C in the format bits.
    #[error("undefined DataFormat {0:#04x}")]
    UnknownFormat(u8),
    /// A sequence of several samples, and no type description to tell where one ends.
    #[error("a sequence of {0} samples needs the type to be split")]
    NeedsType(u32),
    /// Packed samples whose infos differ from the base by more than a delta can express.
    #[error("samples too far apart to be packed")]
    NotPackable,
}

impl SampleError {
    /// A short drop reason.
    pub fn reason(&self) -> &'static str {
        match self {
            SampleError::Decode(e) => e.reason(),
            SampleError::UnknownFormat(_) => "unknown_data_format",
            SampleError::NeedsType(_) => "sample_sequence_needs_type",
            SampleError::NotPackable => "samples_not_packable",
        }
    }
}

/// Whether `format` is one of the five defined DataFormats.
pub fn is_defined_format(format: u8) -> bool {
    matches!(
        format,
        data_format::DATA
            | data_format::SAMPLE
            | data_format::DATA_SEQ
            | data_format::SAMPLE_SEQ
            | data_format::PACKED_SAMPLES
    )
}

/// Takes one SampleData: to the end if it is the last, else as long as the sizer says.
fn take_data<'a>(
    r: &mut CdrReader<'a>,
    last: bool,
    count: u32,
    sizer: Option<SampleSizer<'_>>,
) -> Result<&'a [u8], SampleError> {
    if last {
        return Ok(r.rest());
    }
    let pos = r.position();
    let len = sizer
        .and_then(|s| s(r.clone().rest(), pos))
        .ok_or(SampleError::NeedsType(count))?;
    Ok(r.take(len)?)
}

fn sequence_count(r: &mut CdrReader<'_>) -> Result<u32, SampleError> {
    let count = r.u32()?;
    if count as usize > MAX_SAMPLES || count as usize > r.remaining() + 1 {
        return Err(DecodeError::TooLong("sample sequence").into());
    }
    Ok(count)
}

/// Decodes the bytes after the BaseObjectRequest of a WRITE_DATA or DATA in `format`.
pub fn decode_samples<'a>(
    format: u8,
    data: &'a [u8],
    little_endian: bool,
    dialect: Dialect,
    sizer: Option<SampleSizer<'_>>,
) -> Result<Vec<SampleRef<'a>>, SampleError> {
    let r = &mut CdrReader::new(data, little_endian);
    match format {
        data_format::DATA => Ok(vec![SampleRef { info: None, data }]),
        data_format::SAMPLE => {
            let info = SampleInfo::decode(r, dialect)?;
            Ok(vec![SampleRef {
                info: Some(info),
                data: r.rest(),
            }])
        }
        data_format::DATA_SEQ | data_format::SAMPLE_SEQ => {
            let count = sequence_count(r)?;
            let mut out = Vec::with_capacity(count as usize);
            for i in 0..count {
                let info = if format == data_format::SAMPLE_SEQ {
                    Some(SampleInfo::decode(r, dialect)?)
                } else {
                    None
                };
                let data = take_data(r, i + 1 == count, count, sizer)?;
                out.push(SampleRef { info, data });
            }
            Ok(out)
        }
        data_format::PACKED_SAMPLES => {
            let base = SampleInfo::decode(r, dialect)?;
            let count = sequence_count(r)?;
            let mut out = Vec::with_capacity(count as usize);
            for i in 0..count {
                let delta = SampleInfoDelta {
                    state: r.u8()?,
                    seq_number_delta: r.u8()?,
                    timestamp_delta: r.u16()?,
                };
                let data = take_data(r, i + 1 == count, count, sizer)?;
                out.push(SampleRef {
                    info: Some(delta.apply(&base)),
                    data,
                });
            }
            Ok(out)
        }
        other => Err(SampleError::UnknownFormat(other)),
    }
}

/// Encodes samples in `format` (the bytes that follow the BaseObjectRequest).
///
/// FORMAT_DATA and FORMAT_SAMPLE take exactly one sample; missing infos encode as alive with
/// no detail. PACKED_SAMPLES uses the first sample's info as the base.
pub fn encode_samples(
    format: u8,
    samples: &[SampleRef<'_>],
    little_endian: bool,
    dialect: Dialect,
    out: &mut Vec<u8>,
) -> Result<(), SampleError> {
    let w = &mut CdrWriter::new(out, little_endian);
    let info = |s: &SampleRef<'_>| s.info.unwrap_or_default();
    match format {
        data_format::DATA | data_format::SAMPLE => {
            let [s] = samples else {
                return Err(DecodeError::InvalidValue("one sample expected").into());
            };
            if format == data_format::SAMPLE {
                info(s).encode(w, dialect);
            }
            w.bytes(s.data);
        }
        data_format::DATA_SEQ | data_format::SAMPLE_SEQ => {
            w.u32(samples.len() as u32);
            for s in samples {
                if format == data_format::SAMPLE_SEQ {
                    info(s).encode(w, dialect);
                }
                w.bytes(s.data);
            }
        }
        data_format::PACKED_SAMPLES => {
            let base = samples.first().map(info).unwrap_or_default();
            base.encode(w, dialect);
            w.u32(samples.len() as u32);
            for s in samples {
                let i = info(s);
                let seq_delta = match (base.detail.sequence_number(), i.detail.sequence_number()) {
                    (Some(b), Some(v)) => u8::try_from(v.wrapping_sub(b)).ok(),
                    (None, None) => Some(0),
                    _ => None,
                };
                let time_delta = match (
                    base.detail.session_time_offset(),
                    i.detail.session_time_offset(),
                ) {
                    (Some(b), Some(v)) => {
                        let d = v.wrapping_sub(b);
                        (d % 100 == 0)
                            .then(|| u16::try_from(d / 100).ok())
                            .flatten()
                    }
                    (None, None) => Some(0),
                    _ => None,
                };
                let (Some(seq_number_delta), Some(timestamp_delta)) = (seq_delta, time_delta)
                else {
                    return Err(SampleError::NotPackable);
                };
                w.u8(i.state);
                w.u8(seq_number_delta);
                w.u16(timestamp_delta);
                w.bytes(s.data);
            }
        }
        other => return Err(SampleError::UnknownFormat(other)),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixed(n: usize) -> impl Fn(&[u8], usize) -> Option<usize> {
        move |b: &[u8], _| (b.len() >= n).then_some(n)
    }

    #[test]
    fn spec_and_eprosima_infos_differ_and_roundtrip() {
        let info = SampleInfo {
            state: sample_state::INSTANCE_DISPOSED,
            detail: SampleInfoDetail::Both {
                sequence_number: 7,
                session_time_offset: 1500,
            },
        };
        for (dialect, expected) in [
            (Dialect::Spec, vec![2, 3, 0, 0, 7, 0, 0, 0, 0xDC, 5, 0, 0]),
            (
                Dialect::Eprosima,
                vec![2, 0, 0, 0, 2, 0, 0, 0, 7, 0, 0, 0, 0xDC, 5, 0, 0],
            ),
        ] {
            let mut out = Vec::new();
            info.encode(&mut CdrWriter::new(&mut out, true), dialect);
            assert_eq!(out, expected, "{dialect:?}");
            let back = SampleInfo::decode(&mut CdrReader::new(&out, true), dialect);
            assert_eq!(back, Ok(info));
        }
    }

    #[test]
    fn a_sequence_of_several_needs_the_type() {
        let bytes = [2, 0, 0, 0, 1, 0, 2, 0];
        let r = decode_samples(data_format::DATA_SEQ, &bytes, true, Dialect::Spec, None);
        assert_eq!(r, Err(SampleError::NeedsType(2)));
        let sizer = fixed(2);
        let r = decode_samples(
            data_format::DATA_SEQ,
            &bytes,
            true,
            Dialect::Spec,
            Some(&sizer),
        );
        let r = r.unwrap_or_default();
        assert_eq!(r.len(), 2);
        assert_eq!(r[1].data, &[2, 0]);
    }

    #[test]
    fn a_huge_count_is_refused_without_allocating() {
        let bytes = [0xFF, 0xFF, 0xFF, 0x7F, 1];
        let r = decode_samples(data_format::DATA_SEQ, &bytes, true, Dialect::Spec, None);
        assert!(matches!(r, Err(SampleError::Decode(_))));
    }

    #[test]
    fn undefined_formats_are_refused() {
        for f in [0x04, 0x06, 0x0C] {
            assert_eq!(
                decode_samples(f, &[], true, Dialect::Spec, None),
                Err(SampleError::UnknownFormat(f))
            );
        }
    }
}
