//! Reading the XML representations clients send in CREATE (eProsima / Fast DDS profile form,
//! and the DDS-XRCE form with `topic_ref`).
//!
//! Only what the worker maps to DDS is extracted; unknown elements are ignored, and a
//! document that is not well-formed, or lacks a required element, is an error that names
//! what is missing (the client gets STATUS_ERR_INVALID_DATA or ..._UNKNOWN_REFERENCE).

use roxmltree::{Document, Node};

use crate::backend::policies::*;

/// Why an XML representation was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum XmlError {
    /// Not well-formed XML.
    #[error("malformed XML: {0}")]
    Malformed(String),
    /// A required element or attribute is missing.
    #[error("missing {0}")]
    Missing(&'static str),
    /// A value is not one the agent knows.
    #[error("invalid value {value:?} for {what}")]
    Invalid {
        /// The element or attribute.
        what: &'static str,
        /// Its value.
        value: String,
    },
}

/// A topic as described in XML.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicDesc {
    /// Topic name.
    pub name: String,
    /// Type name.
    pub type_name: String,
    /// `<kind>WITH_KEY</kind>`.
    pub keyed: bool,
    /// QoS given with the topic.
    pub qos: QosDesc,
}

impl TopicDesc {
    /// This topic (a topic object the client created), as an endpoint that names it in its
    /// own `<topic>` element uses it: the element's QoS (Fast DDS puts `historyQos` and
    /// resource limits there) applies to the endpoint, over the topic object's.
    pub fn refined_by(self, endpoint_topic: &TopicDesc) -> TopicDesc {
        TopicDesc {
            qos: self.qos.overridden_by(endpoint_topic.qos),
            ..self
        }
    }
}

/// A data writer or reader as described in XML.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EndpointDesc {
    /// The topic, when described inline.
    pub topic: Option<TopicDesc>,
    /// The topic's name, when referenced (`topic_ref`) instead.
    pub topic_ref: Option<String>,
    /// The client's topic object, when named by id (binary representations).
    pub topic_id: Option<xrce_common::wire::ObjectId>,
    /// Endpoint QoS.
    pub qos: QosDesc,
    /// A data reader's content filter expression (`<content_filter><expression>`).
    pub content_filter: Option<String>,
}

fn parse(xml: &str) -> Result<Document<'_>, XmlError> {
    Document::parse(xml).map_err(|e| XmlError::Malformed(e.to_string()))
}

/// Inserts the whitespace missing between attributes (`a="x"b="y"`), which Fast DDS's XML
/// parser accepts and eProsima's own examples send (C string literals concatenated without a
/// space). `None` if nothing needed fixing.
fn separate_attributes(xml: &str) -> Option<String> {
    let mut out = String::with_capacity(xml.len() + 8);
    let (mut in_tag, mut quote, mut fixed) = (false, None::<char>, false);
    let mut chars = xml.chars().peekable();
    while let Some(c) = chars.next() {
        out.push(c);
        match (in_tag, quote, c) {
            (false, _, '<') => in_tag = true,
            (true, None, '>') => in_tag = false,
            (true, None, '"' | '\'') => quote = Some(c),
            (true, Some(q), c) if c == q => {
                quote = None;
                if chars.peek().is_some_and(|n| n.is_alphabetic() || *n == '_') {
                    out.push(' ');
                    fixed = true;
                }
            }
            _ => {}
        }
    }
    fixed.then_some(out)
}

/// Parses `xml`, forgiving attributes run together; the document may borrow `fixed`.
fn parse_lenient<'a>(
    xml: &'a str,
    fixed: &'a mut Option<String>,
) -> Result<Document<'a>, XmlError> {
    match Document::parse(xml) {
        Ok(d) => Ok(d),
        Err(e) => {
            *fixed = separate_attributes(xml);
            match fixed.as_deref() {
                Some(f) => parse(f),
                None => Err(XmlError::Malformed(e.to_string())),
            }
        }
    }
}

/// Finds the element `name` at the root or under a `<dds>` wrapper (or a profiles library).
fn find<'a>(doc: &'a Document<'a>, name: &str) -> Option<Node<'a, 'a>> {
    doc.root()
        .descendants()
        .find(|n| n.is_element() && n.tag_name().name() == name)
}

fn child<'a>(n: Node<'a, 'a>, name: &str) -> Option<Node<'a, 'a>> {
    n.children()
        .find(|c| c.is_element() && c.tag_name().name() == name)
}

fn text<'a>(n: Node<'a, 'a>, name: &str) -> Option<String> {
    child(n, name)
        .and_then(|c| c.text())
        .map(|t| t.trim().to_string())
        .filter(|t| !t.is_empty())
}

fn upper_kind(n: Node<'_, '_>) -> Option<String> {
    text(n, "kind").map(|k| k.to_ascii_uppercase())
}

/// The first child with any of these names (Fast DDS camelCase or DDS-XML snake_case).
fn child_any<'a>(n: Node<'a, 'a>, names: &[&str]) -> Option<Node<'a, 'a>> {
    names.iter().find_map(|name| child(n, name))
}

fn invalid(what: &'static str, value: impl Into<String>) -> XmlError {
    XmlError::Invalid {
        what,
        value: value.into(),
    }
}

/// A duration element: `<sec>` and `<nanosec>` (either may be `DURATION_INFINITY` or its
/// variants), or a bare number of seconds.
fn parse_period(n: Node<'_, '_>, what: &'static str) -> Result<Period, XmlError> {
    let infinite = |t: &str| t.to_ascii_uppercase().starts_with("DURATION_INFINIT");
    let sec = text(n, "sec").or_else(|| {
        n.text()
            .map(|t| t.trim().to_string())
            .filter(|t| !t.is_empty())
    });
    let nanosec = text(n, "nanosec");
    if sec.as_deref().is_some_and(infinite) || nanosec.as_deref().is_some_and(infinite) {
        return Ok(Period::Infinite);
    }
    let secs: u64 = match sec {
        Some(s) => s.parse().map_err(|_| invalid(what, s))?,
        None => 0,
    };
    let nanos: u32 = match nanosec {
        Some(s) => s
            .parse()
            .ok()
            .filter(|n| *n < 1_000_000_000)
            .ok_or_else(|| invalid(what, s))?,
        None => 0,
    };
    // Durations beyond i32 seconds (about 68 years) are infinite for DDS.
    if secs >= i32::MAX as u64 {
        return Ok(Period::Infinite);
    }
    Ok(Period::Finite(std::time::Duration::new(secs, nanos)))
}

fn parse_bool(n: Node<'_, '_>, name: &str, what: &'static str) -> Result<bool, XmlError> {
    match text(n, name).map(|t| t.to_ascii_lowercase()) {
        None => Ok(false),
        Some(t) if t == "true" || t == "1" => Ok(true),
        Some(t) if t == "false" || t == "0" => Ok(false),
        Some(t) => Err(invalid(what, t)),
    }
}

fn parse_count(n: Node<'_, '_>, name: &str, what: &'static str) -> Result<i32, XmlError> {
    match text(n, name) {
        None => Ok(-1),
        // Fast DDS and DDS both treat zero or negative limits as unlimited.
        Some(t) => t
            .parse::<i64>()
            .map(|v| {
                if v <= 0 {
                    -1
                } else {
                    v.min(i32::MAX as i64) as i32
                }
            })
            .map_err(|_| invalid(what, t)),
    }
}

/// The QoS policies beyond reliability, durability and history.
fn parse_more_qos(h: Node<'_, '_>, q: &mut QosDesc) -> Result<(), XmlError> {
    if let Some(p) = child(h, "deadline").and_then(|d| child(d, "period")) {
        q.deadline = Some(parse_period(p, "deadline period")?);
    }
    if let Some(p) = child(h, "lifespan").and_then(|d| child(d, "duration")) {
        q.lifespan = Some(parse_period(p, "lifespan duration")?);
    }
    if let Some(p) =
        child_any(h, &["latencyBudget", "latency_budget"]).and_then(|d| child(d, "duration"))
    {
        q.latency_budget = Some(parse_period(p, "latency budget duration")?);
    }
    if let Some(p) = child_any(h, &["timeBasedFilter", "time_based_filter"])
        .and_then(|d| child(d, "minimum_separation"))
    {
        q.time_based_filter = Some(parse_period(p, "time-based filter")?);
    }
    if let Some(l) = child(h, "liveliness") {
        let kind = match upper_kind(l)
            .as_deref()
            .map(|k| k.trim_end_matches("_LIVELINESS_QOS"))
        {
            None | Some("AUTOMATIC") => LivelinessKind::Automatic,
            Some("MANUAL_BY_PARTICIPANT") => LivelinessKind::ManualByParticipant,
            Some("MANUAL_BY_TOPIC") => LivelinessKind::ManualByTopic,
            Some(k) => return Err(invalid("liveliness kind", k)),
        };
        let lease = match child(l, "lease_duration") {
            Some(d) => parse_period(d, "liveliness lease duration")?,
            None => Period::Infinite,
        };
        q.liveliness = Some((kind, lease));
    }
    if let Some(k) = child(h, "ownership").and_then(upper_kind) {
        q.ownership = Some(match k.trim_end_matches("_OWNERSHIP_QOS") {
            "SHARED" => OwnershipKind::Shared,
            "EXCLUSIVE" => OwnershipKind::Exclusive,
            _ => return Err(invalid("ownership kind", k)),
        });
    }
    if let Some(v) =
        child_any(h, &["ownershipStrength", "ownership_strength"]).and_then(|s| text(s, "value"))
    {
        q.ownership_strength = Some(v.parse().map_err(|_| invalid("ownership strength", v))?);
    }
    if let Some(k) = child_any(h, &["destinationOrder", "destination_order"]).and_then(upper_kind) {
        q.destination_order = Some(match k.trim_end_matches("_DESTINATIONORDER_QOS") {
            "BY_RECEPTION_TIMESTAMP" => DestinationOrderKind::ByReception,
            "BY_SOURCE_TIMESTAMP" => DestinationOrderKind::BySource,
            _ => return Err(invalid("destination order kind", k)),
        });
    }
    if let Some(r) = child_any(h, &["resourceLimitsQos", "resource_limits"]) {
        q.resource_limits = Some(ResourceLimitsDesc {
            max_samples: parse_count(r, "max_samples", "max_samples")?,
            max_instances: parse_count(r, "max_instances", "max_instances")?,
            max_samples_per_instance: parse_count(
                r,
                "max_samples_per_instance",
                "max_samples_per_instance",
            )?,
        });
    }
    if let Some(p) = child(h, "presentation") {
        let scope = text(p, "access_scope").map(|s| s.to_ascii_uppercase());
        let access_scope = match scope
            .as_deref()
            .map(|s| s.trim_end_matches("_PRESENTATION_QOS"))
        {
            None | Some("INSTANCE") => AccessScope::Instance,
            Some("TOPIC") => AccessScope::Topic,
            Some("GROUP") => AccessScope::Group,
            Some(s) => return Err(invalid("presentation access scope", s)),
        };
        q.presentation = Some(PresentationDesc {
            access_scope,
            coherent_access: parse_bool(p, "coherent_access", "coherent_access")?,
            ordered_access: parse_bool(p, "ordered_access", "ordered_access")?,
        });
    }
    if let Some(p) = child(h, "partition") {
        q.partitions = !partition_names(p).is_empty();
    }
    Ok(())
}

/// The names of a `<partition>` (under `<names>` as Fast DDS writes them, or directly); none
/// if every name is empty (an empty name is the default partition, which alone is no
/// partition at all, and beside others keeps the default partition among them).
fn partition_names(p: Node<'_, '_>) -> Vec<String> {
    let names = child(p, "names").unwrap_or(p);
    let names: Vec<String> = names
        .children()
        .filter(|c| c.is_element() && c.tag_name().name() == "name")
        .map(|c| c.text().unwrap_or("").trim().to_string())
        .collect();
    if names.iter().all(String::is_empty) {
        Vec::new()
    } else {
        names
    }
}

/// The partitions a publisher or subscriber representation names (none: the default
/// partition).
pub fn group_partitions(xml: &str, element: &str) -> Result<Vec<String>, XmlError> {
    let mut fixed = None;
    let doc = parse_lenient(xml, &mut fixed)?;
    let Some(g) = find(&doc, element) else {
        return Ok(Vec::new());
    };
    // Checked like any QoS (a malformed policy is an error), then the names are read.
    parse_qos(g)?;
    let holders = std::iter::once(g).chain(child(g, "qos"));
    Ok(holders
        .filter_map(|h| child(h, "partition"))
        .flat_map(partition_names)
        .collect())
}

fn parse_qos(n: Node<'_, '_>) -> Result<QosDesc, XmlError> {
    let mut q = QosDesc::default();
    // QoS may sit directly under the entity or under a <qos> (Fast DDS) element.
    let holders: Vec<Node<'_, '_>> = std::iter::once(n).chain(child(n, "qos")).collect();
    for h in holders {
        if let Some(k) = child(h, "reliability").and_then(upper_kind) {
            q.reliability = Some(match k.trim_end_matches("_RELIABILITY_QOS") {
                "RELIABLE" => Reliability::Reliable,
                "BEST_EFFORT" => Reliability::BestEffort,
                _ => {
                    return Err(XmlError::Invalid {
                        what: "reliability kind",
                        value: k,
                    })
                }
            });
        }
        if let Some(k) = child(h, "durability").and_then(upper_kind) {
            q.durability = Some(match k.trim_end_matches("_DURABILITY_QOS") {
                "VOLATILE" => Durability::Volatile,
                "TRANSIENT_LOCAL" => Durability::TransientLocal,
                "TRANSIENT" => Durability::Transient,
                "PERSISTENT" => Durability::Persistent,
                _ => {
                    return Err(XmlError::Invalid {
                        what: "durability kind",
                        value: k,
                    })
                }
            });
        }
        if let Some(hist) = child(h, "historyQos").or_else(|| child(h, "history")) {
            let kind = upper_kind(hist).unwrap_or_else(|| "KEEP_LAST".into());
            q.history = Some(match kind.trim_end_matches("_HISTORY_QOS") {
                "KEEP_LAST" => {
                    let depth =
                        match text(hist, "depth") {
                            Some(d) => d.parse::<i32>().ok().filter(|d| *d > 0).ok_or(
                                XmlError::Invalid {
                                    what: "history depth",
                                    value: d,
                                },
                            )?,
                            None => 1,
                        };
                    History::KeepLast(depth)
                }
                "KEEP_ALL" => History::KeepAll,
                _ => {
                    return Err(XmlError::Invalid {
                        what: "history kind",
                        value: kind,
                    })
                }
            });
        }
        parse_more_qos(h, &mut q)?;
    }
    Ok(q)
}

fn parse_topic_node(t: Node<'_, '_>) -> Result<TopicDesc, XmlError> {
    let name = text(t, "name")
        .or_else(|| t.attribute("name").map(str::to_string))
        .ok_or(XmlError::Missing("topic <name>"))?;
    let type_name = text(t, "dataType")
        .or_else(|| t.attribute("register_type_ref").map(str::to_string))
        .ok_or(XmlError::Missing("topic <dataType>"))?;
    let keyed = match upper_kind(t).as_deref() {
        None | Some("NO_KEY") => false,
        Some("WITH_KEY") => true,
        Some(k) => {
            return Err(XmlError::Invalid {
                what: "topic kind",
                value: k.into(),
            })
        }
    };
    Ok(TopicDesc {
        name,
        type_name,
        keyed,
        qos: parse_qos(t)?,
    })
}

/// A requester or replier: the service and its two topics.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServiceDesc {
    /// Service name.
    pub service_name: String,
    /// Request type name.
    pub request_type: String,
    /// Reply type name.
    pub reply_type: String,
    /// Request topic name.
    pub request_topic: String,
    /// Reply topic name.
    pub reply_topic: String,
}

impl ServiceDesc {
    /// A service description; missing topic names follow Fast DDS's defaults
    /// (`<service>_Request`, `<service>_Reply`).
    pub fn new(
        service_name: String,
        request_type: String,
        reply_type: String,
        request_topic: Option<String>,
        reply_topic: Option<String>,
    ) -> Result<Self, XmlError> {
        if service_name.is_empty() || request_type.is_empty() || reply_type.is_empty() {
            return Err(XmlError::Missing(
                "service_name, request_type and reply_type",
            ));
        }
        Ok(ServiceDesc {
            request_topic: request_topic.unwrap_or_else(|| format!("{service_name}_Request")),
            reply_topic: reply_topic.unwrap_or_else(|| format!("{service_name}_Reply")),
            service_name,
            request_type,
            reply_type,
        })
    }
}

/// Parses a `requester` or `replier` representation: attributes `service_name`,
/// `request_type`, `reply_type`, and optional `request_topic_name` / `reply_topic_name`
/// (attributes or child elements, as micro-ROS sends them).
pub fn parse_service(xml: &str, element: &'static str) -> Result<ServiceDesc, XmlError> {
    let mut fixed = None;
    let doc = parse_lenient(xml, &mut fixed)?;
    let e = find(&doc, element).ok_or(XmlError::Missing(element))?;
    let get = |name: &str| {
        e.attribute(name)
            .map(|v| v.trim().to_string())
            .filter(|v| !v.is_empty())
            .or_else(|| text(e, name))
    };
    ServiceDesc::new(
        get("service_name").ok_or(XmlError::Missing("service_name"))?,
        get("request_type").ok_or(XmlError::Missing("request_type"))?,
        get("reply_type").ok_or(XmlError::Missing("reply_type"))?,
        get("request_topic_name"),
        get("reply_topic_name"),
    )
}

/// Parses a participant representation; returns its RTPS name if given.
pub fn parse_participant(xml: &str) -> Result<Option<String>, XmlError> {
    let mut fixed = None;
    let doc = parse_lenient(xml, &mut fixed)?;
    let p = find(&doc, "participant")
        .or_else(|| find(&doc, "domain_participant"))
        .ok_or(XmlError::Missing("<participant>"))?;
    Ok(child(p, "rtps")
        .and_then(|r| text(r, "name"))
        .or_else(|| p.attribute("name").map(str::to_string)))
}

/// Parses a topic representation.
pub fn parse_topic(xml: &str) -> Result<TopicDesc, XmlError> {
    let mut fixed = None;
    let doc = parse_lenient(xml, &mut fixed)?;
    let t = find(&doc, "topic").ok_or(XmlError::Missing("<topic>"))?;
    parse_topic_node(t)
}

/// Parses a `data_writer` or `data_reader` representation.
pub fn parse_endpoint(xml: &str, element: &'static str) -> Result<EndpointDesc, XmlError> {
    let mut fixed = None;
    let doc = parse_lenient(xml, &mut fixed)?;
    let e = find(&doc, element).ok_or(XmlError::Missing(element))?;
    let topic = child(e, "topic").map(parse_topic_node).transpose()?;
    let topic_ref = e.attribute("topic_ref").map(str::to_string);
    if topic.is_none() && topic_ref.is_none() {
        return Err(XmlError::Missing("<topic> or topic_ref"));
    }
    let mut qos = parse_qos(e)?;
    if let Some(q) = e
        .children()
        .find(|c| c.is_element() && c.tag_name().name().ends_with("_qos"))
    {
        qos = qos.overridden_by(parse_qos(q)?);
    }
    let content_filter = child(e, "content_filter")
        .and_then(|f| {
            text(f, "expression").or_else(|| f.attribute("expression").map(str::to_string))
        })
        .map(|x| x.trim().to_string())
        .filter(|x| !x.is_empty());
    Ok(EndpointDesc {
        topic,
        topic_ref,
        topic_id: None,
        qos,
        content_filter,
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn an_endpoint_topic_element_refines_the_topic_object_qos() {
        let object = parse_topic(
            "<dds><topic><name>T</name><dataType>D</dataType>\
             <historyQos><kind>KEEP_LAST</kind><depth>5</depth></historyQos></topic></dds>",
        )
        .expect("topic");
        let writer = parse_endpoint(
            "<dds><data_writer><topic><kind>NO_KEY</kind><name>T</name><dataType>D</dataType>\
             <historyQos><kind>KEEP_LAST</kind><depth>1000</depth></historyQos></topic>\
             <qos><reliability><kind>BEST_EFFORT</kind></reliability></qos></data_writer></dds>",
            "data_writer",
        )
        .expect("writer");
        let inline = writer.topic.as_ref().expect("inline topic");
        let used = object.clone().refined_by(inline);
        assert_eq!(used.name, "T");
        assert_eq!(used.qos.history, Some(History::KeepLast(1000)));
        // Without a history of its own, the endpoint's topic element keeps the object's.
        let plain = parse_endpoint(
            "<dds><data_writer><topic><name>T</name><dataType>D</dataType></topic></data_writer></dds>",
            "data_writer",
        )
        .expect("writer");
        let used = object.refined_by(plain.topic.as_ref().expect("inline topic"));
        assert_eq!(used.qos.history, Some(History::KeepLast(5)));
    }

    use super::*;

    #[test]
    fn reference_client_documents() {
        assert_eq!(
            parse_participant("<dds><participant><rtps><name>default_xrce_participant</name></rtps></participant></dds>"),
            Ok(Some("default_xrce_participant".into()))
        );
        let t = parse_topic(
            "<dds><topic><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic></dds>",
        )
        .expect("topic");
        assert_eq!(
            (t.name.as_str(), t.type_name.as_str(), t.keyed),
            ("HelloWorldTopic", "HelloWorld", false)
        );
        let w = parse_endpoint(
            "<dds><data_writer><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic></data_writer></dds>",
            "data_writer",
        )
        .expect("writer");
        assert_eq!(w.topic.map(|t| t.name), Some("HelloWorldTopic".into()));
        assert_eq!(w.qos, QosDesc::default());
    }

    #[test]
    fn qos_elements() {
        let r = parse_endpoint(
            "<dds><data_reader><topic><kind>WITH_KEY</kind><name>T</name><dataType>Y</dataType>\
             <historyQos><kind>KEEP_LAST</kind><depth>20</depth></historyQos></topic>\
             <qos><reliability><kind>RELIABLE_RELIABILITY_QOS</kind></reliability>\
             <durability><kind>TRANSIENT_LOCAL</kind></durability></qos></data_reader></dds>",
            "data_reader",
        )
        .expect("reader");
        assert_eq!(r.qos.reliability, Some(Reliability::Reliable));
        assert_eq!(r.qos.durability, Some(Durability::TransientLocal));
        let t = r.topic.expect("topic");
        assert!(t.keyed);
        assert_eq!(t.qos.history, Some(History::KeepLast(20)));
    }

    #[test]
    fn every_qos_policy_in_fast_dds_and_dds_xml_spelling() {
        let w = parse_endpoint(
            "<dds><data_writer><topic><name>T</name><dataType>Y</dataType>\
             <resourceLimitsQos><max_samples>100</max_samples><max_instances>0</max_instances>\
             <max_samples_per_instance>10</max_samples_per_instance></resourceLimitsQos></topic>\
             <qos><deadline><period><sec>1</sec><nanosec>500000000</nanosec></period></deadline>\
             <lifespan><duration><sec>DURATION_INFINITY</sec></duration></lifespan>\
             <latencyBudget><duration><sec>0</sec><nanosec>1000</nanosec></duration></latencyBudget>\
             <liveliness><kind>MANUAL_BY_TOPIC_LIVELINESS_QOS</kind><lease_duration><sec>3</sec></lease_duration></liveliness>\
             <ownership><kind>EXCLUSIVE</kind></ownership><ownershipStrength><value>7</value></ownershipStrength>\
             <destinationOrder><kind>BY_SOURCE_TIMESTAMP</kind></destinationOrder>\
             <presentation><access_scope>GROUP</access_scope><coherent_access>true</coherent_access></presentation>\
             </qos></data_writer></dds>",
            "data_writer",
        )
        .expect("writer");
        let q = w.qos;
        let secs = |s: f64| Some(Period::Finite(std::time::Duration::from_secs_f64(s)));
        assert_eq!(q.deadline, secs(1.5));
        assert_eq!(q.lifespan, Some(Period::Infinite));
        assert_eq!(q.latency_budget, secs(0.000001));
        assert_eq!(
            q.liveliness,
            Some((
                LivelinessKind::ManualByTopic,
                Period::Finite(std::time::Duration::from_secs(3))
            ))
        );
        assert_eq!(q.ownership, Some(OwnershipKind::Exclusive));
        assert_eq!(q.ownership_strength, Some(7));
        assert_eq!(q.destination_order, Some(DestinationOrderKind::BySource));
        assert_eq!(
            q.presentation,
            Some(PresentationDesc {
                access_scope: AccessScope::Group,
                coherent_access: true,
                ordered_access: false
            })
        );
        assert!(!q.partitions);
        let t = w.topic.expect("topic");
        assert_eq!(
            t.qos.resource_limits,
            Some(ResourceLimitsDesc {
                max_samples: 100,
                max_instances: -1,
                max_samples_per_instance: 10
            })
        );
        // The DDS-XML (spec) spelling.
        let r = parse_endpoint(
            "<data_reader topic_ref=\"T\"><data_reader_qos><time_based_filter><minimum_separation>\
             <sec>2</sec></minimum_separation></time_based_filter><destination_order>\
             <kind>BY_RECEPTION_TIMESTAMP_DESTINATIONORDER_QOS</kind></destination_order>\
             </data_reader_qos></data_reader>",
            "data_reader",
        )
        .expect("reader");
        assert_eq!(r.qos.time_based_filter, secs(2.0));
        assert_eq!(
            r.qos.destination_order,
            Some(DestinationOrderKind::ByReception)
        );
        // Bad values are refused with what is wrong.
        assert!(matches!(
            parse_endpoint(
                "<data_writer topic_ref=\"T\"><qos><deadline><period><sec>soon</sec></period></deadline></qos></data_writer>",
                "data_writer"
            ),
            Err(XmlError::Invalid { what: "deadline period", .. })
        ));
    }

    #[test]
    fn attributes_run_together_are_accepted_as_fast_dds_does() {
        // eProsima's RequestAdder example, C literals concatenated without a space.
        let s = parse_service(
            "<dds><requester profile_name=\"my_requester\"service_name=\"service_name\"request_type=\"request_type\"reply_type=\"reply_type\"></requester></dds>",
            "requester",
        )
        .expect("requester");
        assert_eq!(s.service_name, "service_name");
        assert_eq!(s.request_topic, "service_name_Request");
        assert_eq!(s.reply_topic, "service_name_Reply");
        // micro-ROS: topic names as child elements.
        let s = parse_service(
            "<dds><replier profile_name=\"0_8\" service_name=\"/add_two_ints\" request_type=\"example_interfaces::srv::dds_::AddTwoInts_Request_\" reply_type=\"example_interfaces::srv::dds_::AddTwoInts_Response_\"><request_topic_name>rq/add_two_intsRequest</request_topic_name><reply_topic_name>rr/add_two_intsReply</reply_topic_name></replier></dds>",
            "replier",
        )
        .expect("replier");
        assert_eq!(s.request_topic, "rq/add_two_intsRequest");
        assert_eq!(s.reply_topic, "rr/add_two_intsReply");
        assert_eq!(separate_attributes("<a b=\"x\"/>"), None);
        assert!(matches!(
            parse_topic("<dds><topic"),
            Err(XmlError::Malformed(_))
        ));
    }

    #[test]
    fn partitions_are_detected() {
        assert_eq!(
            group_partitions(
                "<dds><publisher><qos><partition><names><name>A</name><name> </name><name>B*</name></names></partition></qos></publisher></dds>",
                "publisher"
            ),
            Ok(vec!["A".to_string(), String::new(), "B*".to_string()])
        );
        assert_eq!(
            group_partitions("<dds><publisher/></dds>", "publisher"),
            Ok(Vec::new())
        );
    }

    #[test]
    fn spec_form_with_topic_ref() {
        let w = parse_endpoint(
            "<data_writer name=\"MyWriter\" topic_ref=\"Square\"><data_writer_qos base_name=\"MyQosLib:MyProfile\"><deadline><period><sec>120</sec></period></deadline></data_writer_qos></data_writer>",
            "data_writer",
        )
        .expect("writer");
        assert_eq!(w.topic_ref.as_deref(), Some("Square"));
    }

    #[test]
    fn errors_say_what_is_wrong() {
        assert!(matches!(
            parse_topic("<dds><topic>"),
            Err(XmlError::Malformed(_))
        ));
        assert_eq!(
            parse_topic("<dds><topic><name>x</name></topic></dds>"),
            Err(XmlError::Missing("topic <dataType>"))
        );
        assert!(matches!(
            parse_endpoint("<data_writer topic_ref=\"x\"><qos><reliability><kind>SOMETIMES</kind></reliability></qos></data_writer>", "data_writer"),
            Err(XmlError::Invalid { .. })
        ));
    }
}
