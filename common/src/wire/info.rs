//! `ObjectInfo` of INFO replies (§7.7.12, §8.3.5.7): activity (`ActivityInfoVariant`) and
//! configuration (`ObjectVariant`), in both dialects. The spec orders activity first and
//! frames the `@appendable` activity structs with a DHEADER; eProsima orders the
//! configuration first, writes no DHEADER, and puts DATAWRITER_ActivityInfo's stream
//! sequence number before the sample sequence number (spec-digest §14).
//!
//! Encode and decode with a reader or writer whose origin is the start of the INFO payload,
//! so that alignment matches the wire.

use super::cdr::{CdrReader, CdrWriter};
use super::payload::{decode_properties, encode_properties, ObjectVariant, Property};
use super::types::{object_kind, Dialect};
use super::DecodeError;

/// Most locators accepted in an AGENT_ActivityInfo.
pub const MAX_LOCATORS: usize = 64;

/// `TransportLocator`.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum TransportLocator {
    /// ADDRESS_FORMAT_SMALL.
    Small {
        /// Two address octets.
        address: [u8; 2],
        /// One port octet.
        port: u8,
    },
    /// ADDRESS_FORMAT_MEDIUM (IPv4).
    Medium {
        /// The IPv4 address.
        address: [u8; 4],
        /// The port.
        port: u16,
    },
    /// ADDRESS_FORMAT_LARGE (IPv6).
    Large {
        /// The IPv6 address.
        address: [u8; 16],
        /// The port (four octets on the wire).
        port: u32,
    },
    /// ADDRESS_FORMAT_STRING.
    String(String),
}

impl TransportLocator {
    fn decode(r: &mut CdrReader<'_>) -> Result<Self, DecodeError> {
        Ok(match r.u8()? {
            0 => TransportLocator::Small {
                address: r.array()?,
                port: r.u8()?,
            },
            1 => TransportLocator::Medium {
                address: r.array()?,
                port: r.u16()?,
            },
            2 => TransportLocator::Large {
                address: r.array()?,
                port: r.u32()?,
            },
            3 => TransportLocator::String(r.string(256)?),
            _ => return Err(DecodeError::InvalidValue("TransportLocatorFormat")),
        })
    }

    fn encode(&self, w: &mut CdrWriter<'_>) {
        match self {
            TransportLocator::Small { address, port } => {
                w.u8(0);
                w.bytes(address);
                w.u8(*port);
            }
            TransportLocator::Medium { address, port } => {
                w.u8(1);
                w.bytes(address);
                w.u16(*port);
            }
            TransportLocator::Large { address, port } => {
                w.u8(2);
                w.bytes(address);
                w.u32(*port);
            }
            TransportLocator::String(s) => {
                w.u8(3);
                w.string(s);
            }
        }
    }
}

/// `ActivityInfoVariant`.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum ActivityInfo {
    /// AGENT_ActivityInfo.
    Agent {
        /// > 0: the agent accepts clients.
        availability: i16,
        /// Where it accepts CREATE_CLIENT.
        locators: Vec<TransportLocator>,
    },
    /// DATAWRITER_ActivityInfo.
    DataWriter {
        /// Samples written.
        sample_seq_num: u64,
        /// Stream sequence number.
        stream_seq_num: i16,
    },
    /// DATAREADER_ActivityInfo.
    DataReader {
        /// Highest acknowledged number.
        highest_acked_num: i16,
    },
}

impl ActivityInfo {
    fn kind(&self) -> u8 {
        match self {
            ActivityInfo::Agent { .. } => object_kind::AGENT,
            ActivityInfo::DataWriter { .. } => object_kind::DATAWRITER,
            ActivityInfo::DataReader { .. } => object_kind::DATAREADER,
        }
    }

    /// The struct's members (without discriminator or DHEADER).
    fn encode_members(&self, w: &mut CdrWriter<'_>, dialect: Dialect) {
        match self {
            ActivityInfo::Agent {
                availability,
                locators,
            } => {
                w.i16(*availability);
                w.u32(locators.len() as u32);
                for l in locators {
                    l.encode(w);
                }
            }
            ActivityInfo::DataWriter {
                sample_seq_num,
                stream_seq_num,
            } => match dialect {
                Dialect::Spec => {
                    w.u64_aligned(*sample_seq_num, 4);
                    w.i16(*stream_seq_num);
                }
                Dialect::Eprosima => {
                    w.i16(*stream_seq_num);
                    w.u64_aligned(*sample_seq_num, 8);
                }
            },
            ActivityInfo::DataReader { highest_acked_num } => w.i16(*highest_acked_num),
        }
    }

    fn decode_members(
        kind: u8,
        r: &mut CdrReader<'_>,
        dialect: Dialect,
    ) -> Result<Self, DecodeError> {
        Ok(match kind {
            object_kind::AGENT => {
                let availability = r.i16()?;
                let n = r.u32()? as usize;
                if n > MAX_LOCATORS {
                    return Err(DecodeError::TooLong("locators"));
                }
                let locators = (0..n)
                    .map(|_| TransportLocator::decode(r))
                    .collect::<Result<_, _>>()?;
                ActivityInfo::Agent {
                    availability,
                    locators,
                }
            }
            object_kind::DATAWRITER => match dialect {
                Dialect::Spec => ActivityInfo::DataWriter {
                    sample_seq_num: r.u64_aligned(4)?,
                    stream_seq_num: r.i16()?,
                },
                Dialect::Eprosima => {
                    let stream_seq_num = r.i16()?;
                    ActivityInfo::DataWriter {
                        sample_seq_num: r.u64_aligned(8)?,
                        stream_seq_num,
                    }
                }
            },
            object_kind::DATAREADER => ActivityInfo::DataReader {
                highest_acked_num: r.i16()?,
            },
            _ => return Err(DecodeError::InvalidValue("ActivityInfo kind")),
        })
    }

    /// Encodes the discriminator and the struct (with a DHEADER in the spec dialect).
    pub fn encode(&self, w: &mut CdrWriter<'_>, dialect: Dialect) {
        w.u8(self.kind());
        match dialect {
            Dialect::Eprosima => self.encode_members(w, dialect),
            Dialect::Spec => {
                // DHEADER: the length of what follows it, measured after encoding.
                w.align(4);
                let mut body = Vec::new();
                {
                    // Alignment inside the struct continues the outer stream's (which is
                    // 4-aligned here, and XCDR2 aligns nothing beyond 4).
                    let inner = &mut CdrWriter::new(&mut body, w.is_little_endian());
                    self.encode_members(inner, dialect);
                }
                w.u32(body.len() as u32);
                w.bytes(&body);
            }
        }
    }

    /// Decodes the discriminator and the struct; in the spec dialect the DHEADER bounds it
    /// (members this codec does not know are skipped, as `@appendable` allows).
    pub fn decode(r: &mut CdrReader<'_>, dialect: Dialect) -> Result<Self, DecodeError> {
        let kind = r.u8()?;
        match dialect {
            Dialect::Eprosima => Self::decode_members(kind, r, dialect),
            Dialect::Spec => {
                // Bit 31 is Annex B's bogus "endianness" flag (erratum E25): masked.
                let len = (r.u32()? & 0x7FFF_FFFF) as usize;
                let body = r.take(len)?;
                let inner = &mut CdrReader::new(body, r.is_little_endian());
                Self::decode_members(kind, inner, dialect)
            }
        }
    }
}

/// `AGENT_Representation`.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct AgentRepresentation {
    /// "XRCE".
    pub cookie: [u8; 4],
    /// Protocol version.
    pub version: [u8; 2],
    /// Vendor id.
    pub vendor_id: [u8; 2],
    /// Vendor properties.
    pub properties: Option<Vec<Property>>,
}

/// The configuration member of an ObjectInfo.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum ObjectConfig {
    /// The agent's representation.
    Agent(AgentRepresentation),
    /// A client-created object's description.
    Object(ObjectVariant),
}

impl ObjectConfig {
    fn encode(&self, w: &mut CdrWriter<'_>) {
        match self {
            ObjectConfig::Agent(a) => {
                w.u8(object_kind::AGENT);
                w.bytes(&a.cookie);
                w.bytes(&a.version);
                w.bytes(&a.vendor_id);
                encode_properties(w, &a.properties);
            }
            ObjectConfig::Object(v) => v.encode(w),
        }
    }

    fn decode(r: &mut CdrReader<'_>) -> Result<Self, DecodeError> {
        if r.clone().u8()? == object_kind::AGENT {
            r.u8()?;
            Ok(ObjectConfig::Agent(AgentRepresentation {
                cookie: r.array()?,
                version: r.array()?,
                vendor_id: r.array()?,
                properties: decode_properties(r)?,
            }))
        } else {
            ObjectVariant::decode(r).map(ObjectConfig::Object)
        }
    }
}

/// `ObjectInfo`.
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct ObjectInfo {
    /// What the object is doing.
    pub activity: Option<ActivityInfo>,
    /// How it is configured.
    pub config: Option<ObjectConfig>,
}

impl ObjectInfo {
    /// Encodes in the dialect's member order.
    pub fn encode(&self, w: &mut CdrWriter<'_>, dialect: Dialect) {
        let activity = |w: &mut CdrWriter<'_>| {
            w.bool(self.activity.is_some());
            if let Some(a) = &self.activity {
                a.encode(w, dialect);
            }
        };
        let config = |w: &mut CdrWriter<'_>| {
            w.bool(self.config.is_some());
            if let Some(c) = &self.config {
                c.encode(w);
            }
        };
        match dialect {
            Dialect::Spec => {
                activity(w);
                config(w);
            }
            Dialect::Eprosima => {
                config(w);
                activity(w);
            }
        }
    }

    /// Decodes in the dialect's member order.
    pub fn decode(r: &mut CdrReader<'_>, dialect: Dialect) -> Result<Self, DecodeError> {
        let mut info = ObjectInfo::default();
        let read_activity = |r: &mut CdrReader<'_>| -> Result<Option<ActivityInfo>, DecodeError> {
            if r.bool()? {
                ActivityInfo::decode(r, dialect).map(Some)
            } else {
                Ok(None)
            }
        };
        let read_config = |r: &mut CdrReader<'_>| -> Result<Option<ObjectConfig>, DecodeError> {
            if r.bool()? {
                ObjectConfig::decode(r).map(Some)
            } else {
                Ok(None)
            }
        };
        match dialect {
            Dialect::Spec => {
                info.activity = read_activity(r)?;
                info.config = read_config(r)?;
            }
            Dialect::Eprosima => {
                info.config = read_config(r)?;
                info.activity = read_activity(r)?;
            }
        }
        Ok(info)
    }
}
