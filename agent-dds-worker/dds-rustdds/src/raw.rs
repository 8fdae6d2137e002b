//! Pass-through of serialized samples through RustDDS: the client's CDR bytes go to the wire
//! as they are, and received samples come back as bytes plus their encoding.

use rustdds::bytes::Bytes;
use rustdds::no_key::{Decode, DefaultDecoder, DeserializerAdapter, SerializerAdapter};
use rustdds::RepresentationIdentifier;

use xrce_dds_seam::types::KeyDescriptor;
use xrce_dds_seam::{BackendError, Encoding, Sample};

/// A serialized sample body (no encapsulation header) and its encoding.
#[derive(Debug, Clone)]
pub struct RawSample {
    /// CDR_LE, CDR_BE, ...
    pub encoding: RepresentationIdentifier,
    /// The serialized body.
    pub body: Bytes,
}

impl From<Sample> for RawSample {
    fn from(s: Sample) -> Self {
        RawSample {
            encoding: RepresentationIdentifier::from_bytes(&s.encoding.0)
                .unwrap_or(RepresentationIdentifier::CDR_LE),
            body: s.body,
        }
    }
}

impl From<RawSample> for Sample {
    fn from(s: RawSample) -> Self {
        Sample {
            encoding: Encoding(s.encoding.to_bytes()),
            body: s.body,
        }
    }
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

/// A pass-through serializer: `$adapter` writes `$data` as `$encoding`, its body being
/// what `$body` returns.
macro_rules! pass_through_serializer {
    ($adapter:ty, $data:ty, $encoding:ident, $body:expr) => {
        impl SerializerAdapter<$data> for $adapter {
            type Error = RawError;
            fn output_encoding() -> RepresentationIdentifier {
                RepresentationIdentifier::$encoding
            }
            fn to_bytes(value: &$data) -> Result<Bytes, RawError> {
                let body: fn(&$data) -> &Bytes = $body;
                Ok(body(value).clone())
            }
        }
    };
}

pass_through_serializer!(RawLe, RawSample, CDR_LE, |v| &v.body);
pass_through_serializer!(RawBe, RawSample, CDR_BE, |v| &v.body);

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

/// A serialized sample of a keyed topic, with its key (from the type description).
#[derive(Debug, Clone)]
pub struct RawKeyed {
    /// The sample (for a dispose: the key-only payload).
    pub sample: RawSample,
    /// Its key.
    pub key: RawKey,
}

/// A key: its KeyHash, and the key fields serialized in the writer's encoding.
#[derive(Debug, Clone)]
pub struct RawKey {
    /// The XTypes KeyHash.
    pub hash: [u8; 16],
    /// The key-only payload (what a dispose carries).
    pub payload: Bytes,
}

impl PartialEq for RawKey {
    fn eq(&self, other: &Self) -> bool {
        self.hash == other.hash
    }
}
impl Eq for RawKey {}
impl PartialOrd for RawKey {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for RawKey {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.hash.cmp(&other.hash)
    }
}
impl std::hash::Hash for RawKey {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        self.hash.hash(state)
    }
}
impl serde::Serialize for RawKey {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(&self.payload)
    }
}
impl rustdds::dds::key::CdrEncodingSize for RawKey {
    fn cdr_encoding_max_size() -> rustdds::dds::key::CdrEncodingMaxSize {
        rustdds::dds::key::CdrEncodingMaxSize::Unbounded
    }
}
impl rustdds::Key for RawKey {
    fn hash_key(&self, _force_md5: bool) -> rustdds::dds::key::KeyHash {
        rustdds::dds::key::KeyHash::from_pl_cdr_bytes(self.hash.to_vec())
            .unwrap_or_else(|_| rustdds::dds::key::KeyHash::zero())
    }
}
impl rustdds::Keyed for RawKeyed {
    type K = RawKey;
    fn key(&self) -> RawKey {
        self.key.clone()
    }
}

/// Adapter writing keyed little-endian CDR (XCDR1).
#[derive(Debug)]
pub struct RawKeyedLe;
/// Adapter writing keyed big-endian CDR (XCDR1).
#[derive(Debug)]
pub struct RawKeyedBe;

pass_through_serializer!(RawKeyedLe, RawKeyed, CDR_LE, |v| &v.sample.body);
pass_through_serializer!(RawKeyedBe, RawKeyed, CDR_BE, |v| &v.sample.body);

macro_rules! key_serializer {
    ($adapter:ty) => {
        impl rustdds::with_key::SerializerAdapter<RawKeyed> for $adapter {
            fn key_to_bytes(value: &RawKey) -> Result<Bytes, RawError> {
                Ok(value.payload.clone())
            }
        }
    };
}
key_serializer!(RawKeyedLe);
key_serializer!(RawKeyedBe);

thread_local! {
    /// The key of the topic whose reader is being taken from: RustDDS's default decoder is
    /// a constant, so the type knowledge travels this way (set by [`RawReader::take_next`]).
    static READING_KEY: std::cell::RefCell<Option<std::sync::Arc<KeyDescriptor>>> =
        const { std::cell::RefCell::new(None) };
}

/// Whether an encoding is XCDR version 2.
fn is_xcdr2(encoding: RepresentationIdentifier) -> bool {
    Encoding(encoding.to_bytes()).is_xcdr2()
}

fn key_of(
    body: &[u8],
    encoding: RepresentationIdentifier,
    key_only: bool,
) -> Result<RawKey, RawError> {
    let le = encoding.to_bytes()[1] & 1 == 1;
    READING_KEY.with(|k| {
        let k = k.borrow();
        let k = k
            .as_ref()
            .ok_or(RawError("keyed sample read without its type"))?;
        let key = k
            .of_received(body, le, is_xcdr2(encoding), key_only)
            .map_err(|_| RawError("sample does not match its type"))?;
        Ok(RawKey {
            hash: key.hash,
            payload: Bytes::from(key.payload),
        })
    })
}

impl DeserializerAdapter<RawKeyed> for RawKeyedLe {
    type Error = RawError;
    type Decoded = RawKeyed;
    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &ACCEPTED
    }
    fn transform_decoded(decoded: RawKeyed) -> RawKeyed {
        decoded
    }
}

impl rustdds::with_key::DeserializerAdapter<RawKeyed> for RawKeyedLe {
    type DecodedKey = RawKey;
    fn transform_decoded_key(decoded_key: RawKey) -> RawKey {
        decoded_key
    }
}

/// Decodes keyed samples with the type description of `READING_KEY`.
#[derive(Debug, Clone)]
pub struct RawKeyedDecoder;

impl<'de> Decode<'de, RawKeyed> for RawKeyedDecoder {
    type Error = RawError;
    fn decode_bytes(
        self,
        input: &'de [u8],
        encoding: RepresentationIdentifier,
    ) -> Result<RawKeyed, RawError> {
        Ok(RawKeyed {
            key: key_of(input, encoding, false)?,
            sample: RawSample {
                encoding,
                body: Bytes::copy_from_slice(input),
            },
        })
    }
}

impl<'de> rustdds::with_key::Decode<'de, RawKeyed, RawKey> for RawKeyedDecoder {
    fn decode_key_bytes(
        self,
        input: &'de [u8],
        encoding: RepresentationIdentifier,
    ) -> Result<RawKey, RawError> {
        key_of(input, encoding, true)
    }
}

impl DefaultDecoder<RawKeyed> for RawKeyedLe {
    type Decoder = RawKeyedDecoder;
    const DECODER: RawKeyedDecoder = RawKeyedDecoder;
}

impl rustdds::with_key::DefaultDecoder<RawKeyed> for RawKeyedLe {
    type Decoder = RawKeyedDecoder;
    const DECODER: RawKeyedDecoder = RawKeyedDecoder;
}

/// A sample taken from a [`RawReader`].
#[derive(Debug)]
pub struct Taken {
    /// The sample; for a dispose or unregister, the key-only payload.
    pub sample: RawSample,
    /// DDS sample info.
    pub info: rustdds::SampleInfo,
    /// The instance was disposed (no data).
    pub disposed: bool,
    /// The instance has no writers any more (no data).
    pub unregistered: bool,
}

/// A data reader of raw samples, keyed or not.
pub enum RawReader {
    /// A NO_KEY topic (or a keyed one whose type is unknown).
    NoKey(Box<rustdds::no_key::DataReader<RawSample, RawLe>>),
    /// A WITH_KEY topic with its key description.
    Keyed(
        Box<rustdds::with_key::DataReader<RawKeyed, RawKeyedLe>>,
        std::sync::Arc<KeyDescriptor>,
    ),
}

impl std::fmt::Debug for RawReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RawReader::NoKey(_) => f.write_str("RawReader(no key)"),
            RawReader::Keyed(_, k) => write!(f, "RawReader(key of {})", k.ty().name),
        }
    }
}

impl RawReader {
    /// Creates a reader; keyed when `key` is given.
    pub fn create(
        subscriber: &rustdds::Subscriber,
        topic: &rustdds::Topic,
        qos: rustdds::QosPolicies,
        key: Option<std::sync::Arc<KeyDescriptor>>,
    ) -> rustdds::dds::CreateResult<Self> {
        Ok(match key {
            None => RawReader::NoKey(Box::new(
                subscriber.create_datareader_no_key::<RawSample, RawLe>(topic, Some(qos))?,
            )),
            Some(k) => RawReader::Keyed(
                Box::new(subscriber.create_datareader::<RawKeyed, RawKeyedLe>(topic, Some(qos))?),
                k,
            ),
        })
    }

    /// The reader's GUID.
    pub fn guid(&self) -> rustdds::GUID {
        use rustdds::RTPSEntity;
        match self {
            RawReader::NoKey(r) => r.guid(),
            RawReader::Keyed(r, _) => r.guid(),
        }
    }

    /// Takes the next sample, if any.
    pub fn take_next(&mut self) -> rustdds::dds::ReadResult<Option<Taken>> {
        match self {
            RawReader::NoKey(r) => Ok(r.take_next_sample()?.map(|s| Taken {
                info: s.sample_info().clone(),
                sample: s.into_value(),
                disposed: false,
                unregistered: false,
            })),
            RawReader::Keyed(r, k) => {
                READING_KEY.with(|c| *c.borrow_mut() = Some(k.clone()));
                let s = r.take_next_sample();
                READING_KEY.with(|c| *c.borrow_mut() = None);
                let Some(s) = s? else {
                    return Ok(None);
                };
                let info = s.sample_info().clone();
                let state = info.instance_state();
                Ok(Some(match s.into_value() {
                    rustdds::with_key::Sample::Value(v) => Taken {
                        sample: v.sample,
                        info,
                        disposed: false,
                        unregistered: false,
                    },
                    rustdds::with_key::Sample::Dispose(key) => Taken {
                        sample: RawSample {
                            // The key payload is in this worker's own order (see
                            // KeyDescriptor): little endian.
                            encoding: RepresentationIdentifier::CDR_LE,
                            body: key.payload,
                        },
                        info,
                        disposed: state != rustdds::InstanceState::NotAliveNoWriters,
                        unregistered: state == rustdds::InstanceState::NotAliveNoWriters,
                    },
                }))
            }
        }
    }
}

impl rustdds::mio1::event::Source for RawReader {
    fn register(
        &mut self,
        registry: &rustdds::mio1::Registry,
        token: rustdds::mio1::Token,
        interests: rustdds::mio1::Interest,
    ) -> std::io::Result<()> {
        match self {
            RawReader::NoKey(r) => r.register(registry, token, interests),
            RawReader::Keyed(r, _) => r.register(registry, token, interests),
        }
    }
    fn reregister(
        &mut self,
        registry: &rustdds::mio1::Registry,
        token: rustdds::mio1::Token,
        interests: rustdds::mio1::Interest,
    ) -> std::io::Result<()> {
        match self {
            RawReader::NoKey(r) => r.reregister(registry, token, interests),
            RawReader::Keyed(r, _) => r.reregister(registry, token, interests),
        }
    }
    fn deregister(&mut self, registry: &rustdds::mio1::Registry) -> std::io::Result<()> {
        match self {
            RawReader::NoKey(r) => r.deregister(registry),
            RawReader::Keyed(r, _) => r.deregister(registry),
        }
    }
}

/// A data writer publishing raw samples in the byte order of the client that created it.
pub enum RawWriter {
    /// CDR_LE.
    Le(rustdds::no_key::DataWriter<RawSample, RawLe>),
    /// CDR_BE.
    Be(rustdds::no_key::DataWriter<RawSample, RawBe>),
    /// CDR_LE, keyed.
    KeyedLe(
        rustdds::with_key::DataWriter<RawKeyed, RawKeyedLe>,
        std::sync::Arc<KeyDescriptor>,
    ),
    /// CDR_BE, keyed.
    KeyedBe(
        rustdds::with_key::DataWriter<RawKeyed, RawKeyedBe>,
        std::sync::Arc<KeyDescriptor>,
    ),
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
        key: Option<std::sync::Arc<KeyDescriptor>>,
    ) -> rustdds::dds::CreateResult<Self> {
        if let Some(k) = key {
            return if little_endian {
                publisher
                    .create_datawriter::<RawKeyed, RawKeyedLe>(topic, Some(qos))
                    .map(|w| RawWriter::KeyedLe(w, k))
            } else {
                publisher
                    .create_datawriter::<RawKeyed, RawKeyedBe>(topic, Some(qos))
                    .map(|w| RawWriter::KeyedBe(w, k))
            };
        }
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
        matches!(self, RawWriter::Le(_) | RawWriter::KeyedLe(..))
    }

    /// Whether every matched reliable reader acknowledged everything written (true without
    /// any, and for a best-effort writer). Does not wait.
    pub fn all_acknowledged(&self) -> bool {
        let zero = std::time::Duration::ZERO;
        let r = match self {
            RawWriter::Le(w) => w.wait_for_acknowledgments(zero),
            RawWriter::Be(w) => w.wait_for_acknowledgments(zero),
            RawWriter::KeyedLe(w, _) => w.wait_for_acknowledgments(zero),
            RawWriter::KeyedBe(w, _) => w.wait_for_acknowledgments(zero),
        };
        matches!(r, Ok(true))
    }

    /// The name of the topic it writes.
    pub fn topic_name(&self) -> String {
        use rustdds::TopicDescription;
        match self {
            RawWriter::Le(w) => w.topic().name(),
            RawWriter::Be(w) => w.topic().name(),
            RawWriter::KeyedLe(w, _) => w.topic().name(),
            RawWriter::KeyedBe(w, _) => w.topic().name(),
        }
    }

    /// The key description of a keyed writer.
    pub fn key(&self) -> Option<&std::sync::Arc<KeyDescriptor>> {
        match self {
            RawWriter::KeyedLe(_, k) | RawWriter::KeyedBe(_, k) => Some(k),
            _ => None,
        }
    }

    fn keyed(k: &KeyDescriptor, sample: RawSample) -> Result<RawKeyed, BackendError> {
        let key = k
            .of_sample(&sample.body, sample.little_endian(), false)
            .map_err(|e| {
                BackendError::InvalidInput(format!("key of a {} sample: {e}", k.ty().name))
            })?;
        Ok(RawKeyed {
            sample,
            key: RawKey {
                hash: key.hash,
                payload: Bytes::from(key.payload),
            },
        })
    }

    /// Publishes a sample (already in the writer's byte order).
    pub fn write(&self, sample: RawSample) -> Result<(), BackendError> {
        match self {
            RawWriter::Le(w) => w
                .write(sample, None)
                .map_err(|e| BackendError::Dds(e.to_string())),
            RawWriter::Be(w) => w
                .write(sample, None)
                .map_err(|e| BackendError::Dds(e.to_string())),
            RawWriter::KeyedLe(w, k) => w
                .write(Self::keyed(k, sample)?, None)
                .map_err(|e| BackendError::Dds(e.to_string())),
            RawWriter::KeyedBe(w, k) => w
                .write(Self::keyed(k, sample)?, None)
                .map_err(|e| BackendError::Dds(e.to_string())),
        }
    }

    /// Disposes the instance of `sample` (a whole sample, or its key fields alone). RustDDS
    /// has no unregister; DDS's default `autodispose_unregistered_instances` makes an
    /// unregister a dispose too, which is what callers do.
    pub fn dispose(&self, sample: &RawSample) -> Result<(), BackendError> {
        let Some(k) = self.key() else {
            return Err(BackendError::InvalidInput(
                "dispose on a topic without a key".into(),
            ));
        };
        let le = sample.little_endian();
        let key = k
            .of_sample(&sample.body, le, false)
            .or_else(|_| k.of_key_payload(&sample.body, le, false))
            .map_err(|e| {
                BackendError::InvalidInput(format!("key of a {} sample: {e}", k.ty().name))
            })?;
        let key = RawKey {
            hash: key.hash,
            payload: Bytes::from(key.payload),
        };
        match self {
            RawWriter::KeyedLe(w, _) => w
                .dispose(&key, None)
                .map_err(|e| BackendError::Dds(e.to_string())),
            RawWriter::KeyedBe(w, _) => w
                .dispose(&key, None)
                .map_err(|e| BackendError::Dds(e.to_string())),
            _ => Err(BackendError::InvalidInput(
                "dispose on a topic without a key".into(),
            )),
        }
    }

    /// Publishes a sample, optionally as the reply to `related`; returns its identity.
    pub fn write_identified(
        &self,
        sample: RawSample,
        related: Option<rustdds::SampleIdentity>,
    ) -> Result<rustdds::SampleIdentity, BackendError> {
        let opts = rustdds::WriteOptionsBuilder::new()
            .related_sample_identity_opt(related)
            .build();
        match self {
            RawWriter::Le(w) => w
                .write_with_options(sample, opts)
                .map_err(|e| BackendError::Dds(e.to_string())),
            RawWriter::Be(w) => w
                .write_with_options(sample, opts)
                .map_err(|e| BackendError::Dds(e.to_string())),
            RawWriter::KeyedLe(w, k) => w
                .write_with_options(Self::keyed(k, sample)?, opts)
                .map_err(|e| BackendError::Dds(e.to_string())),
            RawWriter::KeyedBe(w, k) => w
                .write_with_options(Self::keyed(k, sample)?, opts)
                .map_err(|e| BackendError::Dds(e.to_string())),
        }
    }

    /// The writer's GUID (requests are matched to replies by it).
    pub fn guid(&self) -> rustdds::GUID {
        use rustdds::RTPSEntity;
        match self {
            RawWriter::Le(w) => w.guid(),
            RawWriter::Be(w) => w.guid(),
            RawWriter::KeyedLe(w, _) => w.guid(),
            RawWriter::KeyedBe(w, _) => w.guid(),
        }
    }

    /// The next status event, if any.
    pub fn try_recv_status(&self) -> Option<rustdds::dds::statusevents::DataWriterStatus> {
        use rustdds::StatusEvented;
        match self {
            RawWriter::Le(w) => w.try_recv_status(),
            RawWriter::Be(w) => w.try_recv_status(),
            RawWriter::KeyedLe(w, _) => w.try_recv_status(),
            RawWriter::KeyedBe(w, _) => w.try_recv_status(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rustdds_encodings_keep_their_byte_order_and_version_through_the_seam() {
        for (rep, le, xcdr2) in [
            (RepresentationIdentifier::CDR_LE, true, false),
            (RepresentationIdentifier::CDR_BE, false, false),
            (RepresentationIdentifier::XCDR2_LE, true, true),
            (RepresentationIdentifier::XCDR2_BE, false, true),
        ] {
            assert!(ACCEPTED.contains(&rep));
            let sample = Sample::from(RawSample {
                encoding: rep,
                body: Bytes::from_static(&[1, 2]),
            });
            assert_eq!(
                (sample.little_endian(), sample.encoding.is_xcdr2()),
                (le, xcdr2),
                "{rep:?}"
            );
            assert_eq!(is_xcdr2(rep), xcdr2);
            assert_eq!(RawSample::from(sample).encoding, rep);
        }
    }
}
