//! Pass-through of serialized samples through RustDDS: the client's CDR bytes go to the wire
//! as they are, and received samples come back as bytes plus their encoding.

use rustdds::bytes::Bytes;
use rustdds::no_key::{Decode, DefaultDecoder, DeserializerAdapter, SerializerAdapter};
use rustdds::RepresentationIdentifier;

/// A serialized sample body (no encapsulation header) and its encoding.
#[derive(Debug, Clone)]
pub struct RawSample {
    /// CDR_LE, CDR_BE, ...
    pub encoding: RepresentationIdentifier,
    /// The serialized body.
    pub body: Bytes,
}

impl RawSample {
    /// Whether the body is little endian.
    pub fn little_endian(&self) -> bool {
        // Every representation identifier ends in 1 for little endian.
        self.encoding.to_bytes()[1] & 1 == 1
    }
}

/// Errors never happen for pass-through; RustDDS's traits need a type anyway.
#[derive(Debug, thiserror::Error)]
#[error("raw sample adapter: {0}")]
pub struct RawError(&'static str);

/// Adapter writing little-endian CDR (XCDR1).
#[derive(Debug)]
pub struct RawLe;
/// Adapter writing big-endian CDR (XCDR1).
#[derive(Debug)]
pub struct RawBe;

impl SerializerAdapter<RawSample> for RawLe {
    type Error = RawError;
    fn output_encoding() -> RepresentationIdentifier {
        RepresentationIdentifier::CDR_LE
    }
    fn to_bytes(value: &RawSample) -> Result<Bytes, RawError> {
        Ok(value.body.clone())
    }
}

impl SerializerAdapter<RawSample> for RawBe {
    type Error = RawError;
    fn output_encoding() -> RepresentationIdentifier {
        RepresentationIdentifier::CDR_BE
    }
    fn to_bytes(value: &RawSample) -> Result<Bytes, RawError> {
        Ok(value.body.clone())
    }
}

static ACCEPTED: [RepresentationIdentifier; 4] = [
    RepresentationIdentifier::CDR_LE,
    RepresentationIdentifier::CDR_BE,
    RepresentationIdentifier::XCDR2_LE,
    RepresentationIdentifier::XCDR2_BE,
];

impl DeserializerAdapter<RawSample> for RawLe {
    type Error = RawError;
    type Decoded = RawSample;
    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &ACCEPTED
    }
    fn transform_decoded(decoded: RawSample) -> RawSample {
        decoded
    }
}

/// Copies received bytes into a [`RawSample`].
#[derive(Debug, Clone)]
pub struct RawDecoder;

impl<'de> Decode<'de, RawSample> for RawDecoder {
    type Error = RawError;
    fn decode_bytes(
        self,
        input: &'de [u8],
        encoding: RepresentationIdentifier,
    ) -> Result<RawSample, RawError> {
        Ok(RawSample {
            encoding,
            body: Bytes::copy_from_slice(input),
        })
    }
}

impl DefaultDecoder<RawSample> for RawLe {
    type Decoder = RawDecoder;
    const DECODER: RawDecoder = RawDecoder;
}

/// A data writer publishing raw samples in the byte order of the client that created it.
pub enum RawWriter {
    /// CDR_LE.
    Le(rustdds::no_key::DataWriter<RawSample, RawLe>),
    /// CDR_BE.
    Be(rustdds::no_key::DataWriter<RawSample, RawBe>),
}

impl std::fmt::Debug for RawWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.little_endian() {
            "RawWriter(CDR_LE)"
        } else {
            "RawWriter(CDR_BE)"
        })
    }
}

impl RawWriter {
    /// A writer on `topic` publishing in the given byte order (a client's native one).
    pub fn create(
        publisher: &rustdds::Publisher,
        topic: &rustdds::Topic,
        qos: rustdds::QosPolicies,
        little_endian: bool,
    ) -> rustdds::dds::CreateResult<Self> {
        if little_endian {
            publisher
                .create_datawriter_no_key::<RawSample, RawLe>(topic, Some(qos))
                .map(RawWriter::Le)
        } else {
            publisher
                .create_datawriter_no_key::<RawSample, RawBe>(topic, Some(qos))
                .map(RawWriter::Be)
        }
    }

    /// Whether it publishes little-endian samples.
    pub fn little_endian(&self) -> bool {
        matches!(self, RawWriter::Le(_))
    }

    /// Publishes a sample (already in the writer's byte order).
    pub fn write(&self, sample: RawSample) -> Result<(), String> {
        match self {
            RawWriter::Le(w) => w.write(sample, None).map_err(|e| e.to_string()),
            RawWriter::Be(w) => w.write(sample, None).map_err(|e| e.to_string()),
        }
    }

    /// Publishes a sample, optionally as the reply to `related`; returns its identity.
    pub fn write_identified(
        &self,
        sample: RawSample,
        related: Option<rustdds::SampleIdentity>,
    ) -> Result<rustdds::SampleIdentity, String> {
        let opts = rustdds::WriteOptionsBuilder::new()
            .related_sample_identity_opt(related)
            .build();
        match self {
            RawWriter::Le(w) => w
                .write_with_options(sample, opts)
                .map_err(|e| e.to_string()),
            RawWriter::Be(w) => w
                .write_with_options(sample, opts)
                .map_err(|e| e.to_string()),
        }
    }

    /// The writer's GUID (requests are matched to replies by it).
    pub fn guid(&self) -> rustdds::GUID {
        use rustdds::RTPSEntity;
        match self {
            RawWriter::Le(w) => w.guid(),
            RawWriter::Be(w) => w.guid(),
        }
    }

    /// The next status event, if any.
    pub fn try_recv_status(&self) -> Option<rustdds::dds::statusevents::DataWriterStatus> {
        use rustdds::StatusEvented;
        match self {
            RawWriter::Le(w) => w.try_recv_status(),
            RawWriter::Be(w) => w.try_recv_status(),
        }
    }
}

/// A `SampleIdentity` as eProsima's client carries it in front of request and reply data:
/// the writer GUID's 16 octets, then the sequence number as `int32 high`, `uint32 low` in the
/// given byte order (24 bytes).
pub fn encode_sample_identity(id: &rustdds::SampleIdentity, little_endian: bool) -> [u8; 24] {
    let mut out = [0u8; 24];
    out[..16].copy_from_slice(&id.writer_guid.to_bytes());
    let (high, low) = (id.sequence_number.high(), id.sequence_number.low());
    let (h, l) = if little_endian {
        (high.to_le_bytes(), low.to_le_bytes())
    } else {
        (high.to_be_bytes(), low.to_be_bytes())
    };
    out[16..20].copy_from_slice(&h);
    out[20..24].copy_from_slice(&l);
    out
}

/// Reads the 24-byte identity [`encode_sample_identity`] writes; `None` if too short.
pub fn decode_sample_identity(b: &[u8], little_endian: bool) -> Option<rustdds::SampleIdentity> {
    let guid: [u8; 16] = b.get(..16)?.try_into().ok()?;
    let h: [u8; 4] = b.get(16..20)?.try_into().ok()?;
    let l: [u8; 4] = b.get(20..24)?.try_into().ok()?;
    let (high, low) = if little_endian {
        (i32::from_le_bytes(h), u32::from_le_bytes(l))
    } else {
        (i32::from_be_bytes(h), u32::from_be_bytes(l))
    };
    Some(rustdds::SampleIdentity {
        writer_guid: rustdds::GUID::from_bytes(guid),
        sequence_number: rustdds::SequenceNumber::from_high_low(high, low),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sample_identities_round_trip_in_both_byte_orders() {
        let id = rustdds::SampleIdentity {
            writer_guid: rustdds::GUID::from_bytes([7; 16]),
            sequence_number: rustdds::SequenceNumber::from_high_low(1, 0x0102_0304),
        };
        for le in [true, false] {
            let b = encode_sample_identity(&id, le);
            assert_eq!(decode_sample_identity(&b, le), Some(id));
        }
        assert_eq!(&encode_sample_identity(&id, true)[20..], &[4, 3, 2, 1]);
        assert_eq!(decode_sample_identity(&[0; 23], true), None);
    }
}
