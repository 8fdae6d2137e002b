//! The worker's view of DDS: the seam every backend implements (`xrce_dds_seam`, re-exported
//! here) and the choice of implementation.
//!
//! The worker's modules use only the seam's traits and types; [`create`] makes the backend
//! the configuration names (`WorkerProcess::start`), `Worker::new` takes any backend. The
//! implementations are crates of their own: `xrce_dds_cyclone` (Cyclone DDS, the default,
//! with the `cyclone` feature, on by default), `xrce_dds_rustdds` (RustDDS, always built; it
//! also serves requesters and repliers beside a backend that cannot, [`for_services`], and
//! delivers between the worker's own writers and readers inside the process) and
//! `xrce_dds_zenoh` (rmw_zenoh's conventions, the `zenoh` feature).

pub use xrce_dds_seam::*;

/// The DDS implementations a worker can use. The default is Cyclone DDS when the build has
/// it (the `cyclone` feature, on by default), RustDDS otherwise.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// RustDDS (always built).
    #[cfg_attr(not(feature = "cyclone"), default)]
    Rustdds,
    /// Cyclone DDS (built with the `cyclone` feature).
    #[cfg_attr(feature = "cyclone", default)]
    Cyclone,
    /// Zenoh, as ROS 2's rmw_zenoh uses it (built with the `zenoh` feature; `-m zenoh`).
    Zenoh,
}

impl BackendKind {
    /// Its name on the command line.
    pub fn as_str(self) -> &'static str {
        match self {
            BackendKind::Rustdds => "rustdds",
            BackendKind::Cyclone => "cyclone",
            BackendKind::Zenoh => "zenoh",
        }
    }

    /// Whether this build has it.
    pub fn is_built(self) -> bool {
        match self {
            BackendKind::Rustdds => true,
            BackendKind::Cyclone => cfg!(feature = "cyclone"),
            BackendKind::Zenoh => cfg!(feature = "zenoh"),
        }
    }
}

/// Refuses a configuration DDS cannot be confined by (`--dds-interface`: an address this
/// host does not hold, too many, no socket filters; see [`confine`]), or that the backend
/// cannot use (Cyclone DDS: IPv4 and IPv6 addresses together), before anything is made:
/// the worker then refuses to start rather than run DDS on interfaces it was not given.
pub fn check_config(backend: BackendKind, config: &DdsConfig) -> anyhow::Result<()> {
    use anyhow::Context as _;
    let plan = confine::check(&config.interfaces).with_context(|| {
        format!(
            "cannot confine DDS to --dds-interface {}",
            config
                .interfaces
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join(",")
        )
    })?;
    match plan {
        confine::Plan::Everywhere if config.interfaces.is_empty() => {}
        confine::Plan::Everywhere => {
            tracing::info!("DDS on every interface (an unspecified --dds-interface address)")
        }
        confine::Plan::Confined {
            addresses,
            interfaces,
            ..
        } => tracing::info!(
            ?addresses,
            ?interfaces,
            "DDS confined to these addresses and interfaces"
        ),
    }
    #[cfg(not(feature = "cyclone"))]
    let _ = backend;
    #[cfg(feature = "cyclone")]
    if backend == BackendKind::Cyclone {
        xrce_dds_cyclone::config_xml(&config.interfaces, None, None)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    Ok(())
}

/// Refuses, before anything starts, what would stop a Zenoh backend at its start: a Zenoh
/// configuration (`ZENOH_SESSION_CONFIG_URI`, `ZENOH_CONFIG_OVERRIDE`) it cannot use, or a
/// `--zenoh-type-hashes` path that is neither a folder nor a readable table.
pub fn check_zenoh(type_hashes: &[std::path::PathBuf]) -> anyhow::Result<()> {
    #[cfg(feature = "zenoh")]
    {
        let env = |name: &str| std::env::var(name).ok();
        xrce_dds_zenoh::session::config(
            env(xrce_dds_zenoh::session::CONFIG_URI_ENV).as_deref(),
            env(xrce_dds_zenoh::session::CONFIG_OVERRIDE_ENV).as_deref(),
        )?;
        xrce_dds_zenoh::type_hashes::TypeHashes::new(type_hashes, None)?;
        Ok(())
    }
    #[cfg(not(feature = "zenoh"))]
    {
        let _ = type_hashes;
        anyhow::bail!("this build has no Zenoh backend: build it with the `zenoh` feature")
    }
}

/// The domains DDS cannot serve with this configuration, with why: those whose discovery
/// multicast port a front-end serves XRCE on ([`ports::unservable_domains`]; none with Zenoh,
/// which uses no DDS port).
pub fn unservable_domains(
    backend: BackendKind,
    config: &DdsConfig,
) -> std::collections::BTreeMap<u16, String> {
    if backend == BackendKind::Zenoh {
        return Default::default();
    }
    ports::unservable_domains(&config.reserved_ports, &config.interfaces)
}

/// The backend `backend` names, once [`check_config`] accepted the configuration.
pub fn create(backend: BackendKind, config: &DdsConfig) -> anyhow::Result<Box<dyn DdsBackend>> {
    check_config(backend, config)?;
    ports::log_reserved(&config.reserved_ports, &config.interfaces);
    match backend {
        BackendKind::Rustdds => rustdds_delivering_locally(config.clone()),
        #[cfg(feature = "cyclone")]
        BackendKind::Cyclone => Ok(Box::new(xrce_dds_cyclone::Cyclone::new(config.clone())?)),
        #[cfg(not(feature = "cyclone"))]
        BackendKind::Cyclone => anyhow::bail!(
            "this build has no Cyclone DDS backend: build it with the `cyclone` feature \
             (on by default; needs cmake and libclang: deploy/build-deps), or use \
             --dds-backend rustdds"
        ),
        #[cfg(feature = "zenoh")]
        BackendKind::Zenoh => Ok(Box::new(xrce_dds_zenoh::Zenoh::new(config)?)),
        #[cfg(not(feature = "zenoh"))]
        BackendKind::Zenoh => anyhow::bail!(
            "this build has no Zenoh backend: build it with the `zenoh` feature (on by default)"
        ),
    }
}

/// A backend for requesters and repliers, beside one that cannot serve them
/// ([`DdsBackend::supports_services`] false): RustDDS, which puts a reply's related sample
/// identity on the wire (Fast DDS's convention, what eProsima's client and agent use) and
/// reports it, in the same domains and on the same interfaces.
pub fn for_services(config: &DdsConfig) -> anyhow::Result<Box<dyn DdsBackend>> {
    check_config(BackendKind::Rustdds, config)?;
    rustdds_delivering_locally(config.clone())
}

/// The RustDDS backend, which sends samples between its own writers and readers through
/// UDP loopback, wrapped so that they are delivered inside the process
/// (`xrce_dds_rustdds::local`), unless the configuration says otherwise
/// ([`DdsConfig::rustdds_loopback`]).
fn rustdds_delivering_locally(config: DdsConfig) -> anyhow::Result<Box<dyn DdsBackend>> {
    let loopback = config.rustdds_loopback;
    let rustdds = Box::new(xrce_dds_rustdds::RustDds::new(config)?);
    if loopback {
        tracing::info!("local delivery off: RustDDS delivers the agent's own samples");
        return Ok(rustdds);
    }
    Ok(Box::new(xrce_dds_rustdds::local::LocalDelivery::new(
        rustdds,
    )))
}

/// The domain id XRCE clients use to mean "the agent's default" (reference agent behaviour).
pub const DOMAIN_ID_DEFAULT_MARKER: i16 = 255;

/// Maps the domain id a client asked for to the DDS domain used: the marker of "the agent's
/// default" to `default` (`--default-domain`, else ROS_DOMAIN_ID, else 0), another id to
/// itself if DDS allows it.
pub fn effective_domain(requested: i16, default: u16) -> Result<u16, String> {
    if requested == DOMAIN_ID_DEFAULT_MARKER {
        return Ok(default);
    }
    u16::try_from(requested)
        .ok()
        .filter(|d| *d <= crate::domains::MAX_DOMAIN_ID)
        .ok_or_else(|| format!("domain id {requested} out of range"))
}

/// A `SampleIdentity` as eProsima's client carries it in front of request and reply data:
/// the writer GUID's 16 octets, then the sequence number as `int32 high`, `uint32 low` in the
/// given byte order (24 bytes).
pub fn encode_sample_identity(id: &SampleIdentity, little_endian: bool) -> [u8; 24] {
    let mut out = [0u8; 24];
    out[..16].copy_from_slice(&id.writer);
    let (high, low) = ((id.sequence_number >> 32) as i32, id.sequence_number as u32);
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
pub fn decode_sample_identity(b: &[u8], little_endian: bool) -> Option<SampleIdentity> {
    let writer: [u8; 16] = b.get(..16)?.try_into().ok()?;
    let h: [u8; 4] = b.get(16..20)?.try_into().ok()?;
    let l: [u8; 4] = b.get(20..24)?.try_into().ok()?;
    let (high, low) = if little_endian {
        (i32::from_le_bytes(h), u32::from_le_bytes(l))
    } else {
        (i32::from_be_bytes(h), u32::from_be_bytes(l))
    };
    Some(SampleIdentity {
        writer,
        sequence_number: (i64::from(high) << 32) | i64::from(low),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::representation::OpError;
    use xrce_common::wire::status;

    #[test]
    fn only_input_the_backend_cannot_take_is_the_clients_fault() {
        let input = BackendError::InvalidInput("key of a Keyed sample: too short".into());
        let with_context = input.context("DDS write");
        assert_eq!(
            with_context,
            BackendError::InvalidInput("DDS write: key of a Keyed sample: too short".into())
        );
        assert_eq!(
            OpError::from(with_context).status(),
            status::ERR_INVALID_DATA
        );
        for other in [
            BackendError::Dds("create data writer: out of resources".into()),
            BackendError::Placement("UDP port 7401 is taken".into()),
            BackendError::Unsupported("no services here"),
            BackendError::ForeignEntity("a data writer needs a publisher of this backend"),
        ] {
            let op = OpError::from(other.clone().context("DDS write"));
            assert_eq!(op.status(), status::ERR_DDS_ERROR, "{other:?}");
            assert!(op.to_string().starts_with("DDS write: "), "{op}");
        }
    }

    #[test]
    fn sample_identities_round_trip_in_both_byte_orders() {
        let id = SampleIdentity {
            writer: [7; 16],
            sequence_number: (1 << 32) | 0x0102_0304,
        };
        for le in [true, false] {
            let b = encode_sample_identity(&id, le);
            assert_eq!(decode_sample_identity(&b, le), Some(id));
        }
        assert_eq!(
            &encode_sample_identity(&id, true)[16..],
            &[1, 0, 0, 0, 4, 3, 2, 1]
        );
        assert_eq!(
            &encode_sample_identity(&id, false)[16..],
            &[0, 0, 0, 1, 1, 2, 3, 4]
        );
        let negative = SampleIdentity {
            writer: [1; 16],
            sequence_number: -2,
        };
        assert_eq!(
            decode_sample_identity(&encode_sample_identity(&negative, true), true),
            Some(negative)
        );
        assert_eq!(decode_sample_identity(&[0; 23], true), None);
    }

    #[test]
    fn domain_ids() {
        assert_eq!(effective_domain(7, 3), Ok(7));
        assert_eq!(effective_domain(DOMAIN_ID_DEFAULT_MARKER, 3), Ok(3));
        assert!(effective_domain(-1, 0).is_err());
        assert!(effective_domain(300, 0).is_err());
    }
}
