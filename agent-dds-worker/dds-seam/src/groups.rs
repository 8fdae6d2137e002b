//! Publishers and subscribers, typed by role.
//!
//! A backend makes its groups and endpoints with its own types ([`Endpoints`]: a publisher
//! type that only data writers are made in, a subscriber type for data readers). The worker
//! holds them as [`Publisher`] and [`Subscriber`], which say their role in their type and
//! keep the backend's own group inside; [`DynEndpoints`], implemented once here for every
//! [`Endpoints`], gives the backend its own group back. So no backend looks for its types
//! at run time, a data writer cannot be asked of a subscriber, and a group made by a backend
//! of another type is refused in one place ([`BackendError::ForeignEntity`]).

use std::any::Any;

use crate::{BackendError, DdsReader, DdsWriter, EndpointQos, ReaderToken, TopicSpec};

/// A DDS publisher on the participant of a domain, as the worker holds it: data writers are
/// made in it ([`DynEndpoints::create_writer`]); dropping it (after its writers) deletes it.
pub struct Publisher {
    domain: u16,
    group: Box<dyn Any>,
}

/// A DDS subscriber on the participant of a domain, as the worker holds it: data readers
/// are made in it ([`DynEndpoints::create_reader`]); dropping it (after its readers)
/// deletes it.
pub struct Subscriber {
    domain: u16,
    group: Box<dyn Any>,
}

impl Publisher {
    /// The domain it is in.
    pub fn domain(&self) -> u16 {
        self.domain
    }
}

impl Subscriber {
    /// The domain it is in.
    pub fn domain(&self) -> u16 {
        self.domain
    }
}

impl std::fmt::Debug for Publisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Publisher")
            .field("domain", &self.domain)
            .finish_non_exhaustive()
    }
}

impl std::fmt::Debug for Subscriber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Subscriber")
            .field("domain", &self.domain)
            .finish_non_exhaustive()
    }
}

/// How a backend makes publishers, subscribers and their endpoints, with its own types (the
/// worker calls them as [`DynEndpoints`]' `create_*`).
pub trait Endpoints {
    /// Its publisher (one type may serve both roles: the seam keeps the roles apart).
    type Publisher: 'static;
    /// Its subscriber.
    type Subscriber: 'static;
    /// A publisher in `domain` with the given partitions (empty: the default partition; only
    /// asked of a backend that [supports them](crate::DdsBackend::supports_partitions)),
    /// making the domain's participant on first use.
    fn new_publisher(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Self::Publisher, BackendError>;
    /// A subscriber, as [`new_publisher`](Endpoints::new_publisher).
    fn new_subscriber(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Self::Subscriber, BackendError>;
    /// A data writer in `publisher` publishing in the given byte order.
    fn new_writer(
        &mut self,
        publisher: &Self::Publisher,
        domain: u16,
        topic: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError>;
    /// A data reader in `subscriber`, whose data wakes the loop with `token`.
    fn new_reader(
        &mut self,
        subscriber: &Self::Subscriber,
        domain: u16,
        topic: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError>;
}

/// [`Endpoints`] as the worker calls it through `dyn DdsBackend`: implemented here for every
/// backend, never by one.
pub trait DynEndpoints {
    /// A publisher in `domain` ([`Endpoints::new_publisher`]).
    fn create_publisher(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Publisher, BackendError>;
    /// A subscriber in `domain` ([`Endpoints::new_subscriber`]).
    fn create_subscriber(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Subscriber, BackendError>;
    /// A data writer in `publisher`, which this backend made.
    fn create_writer(
        &mut self,
        publisher: &Publisher,
        topic: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError>;
    /// A data reader in `subscriber`, which this backend made.
    fn create_reader(
        &mut self,
        subscriber: &Subscriber,
        topic: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError>;
}

impl<B: Endpoints> DynEndpoints for B {
    fn create_publisher(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Publisher, BackendError> {
        let group = Endpoints::new_publisher(self, domain, partitions)?;
        Ok(Publisher {
            domain,
            group: Box::new(group),
        })
    }

    fn create_subscriber(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Subscriber, BackendError> {
        let group = Endpoints::new_subscriber(self, domain, partitions)?;
        Ok(Subscriber {
            domain,
            group: Box::new(group),
        })
    }

    fn create_writer(
        &mut self,
        publisher: &Publisher,
        topic: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError> {
        let Some(group) = publisher.group.downcast_ref::<B::Publisher>() else {
            return Err(BackendError::ForeignEntity(
                "a data writer needs a publisher of this backend",
            ));
        };
        Endpoints::new_writer(self, group, publisher.domain, topic, qos, little_endian)
    }

    fn create_reader(
        &mut self,
        subscriber: &Subscriber,
        topic: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError> {
        let Some(group) = subscriber.group.downcast_ref::<B::Subscriber>() else {
            return Err(BackendError::ForeignEntity(
                "a data reader needs a subscriber of this backend",
            ));
        };
        Endpoints::new_reader(self, group, subscriber.domain, topic, qos, token)
    }
}
