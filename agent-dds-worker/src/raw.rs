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

    /// The next status event, if any.
    pub fn try_recv_status(&self) -> Option<rustdds::dds::statusevents::DataWriterStatus> {
        use rustdds::StatusEvented;
        match self {
            RawWriter::Le(w) => w.try_recv_status(),
            RawWriter::Be(w) => w.try_recv_status(),
        }
    }
}
