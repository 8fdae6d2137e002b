//! Reading the XML representations clients send in CREATE (eProsima / Fast DDS profile form,
//! and the DDS-XRCE form with `topic_ref`).
//!
//! Only what the worker maps to DDS is extracted; unknown elements are ignored, and a
//! document that is not well-formed, or lacks a required element, is an error that names
//! what is missing (the client gets STATUS_ERR_INVALID_DATA or ..._UNKNOWN_REFERENCE).

use roxmltree::{Document, Node};

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
    Invalid { what: &'static str, value: String },
}

/// Reliability kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reliability {
    /// RELIABLE.
    Reliable,
    /// BEST_EFFORT.
    BestEffort,
}

/// Durability kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Durability {
    /// VOLATILE.
    Volatile,
    /// TRANSIENT_LOCAL.
    TransientLocal,
    /// TRANSIENT.
    Transient,
    /// PERSISTENT.
    Persistent,
}

/// History kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum History {
    /// KEEP_LAST with a depth.
    KeepLast(i32),
    /// KEEP_ALL.
    KeepAll,
}

/// QoS settings found in a representation (absent = the entity's default).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct QosDesc {
    /// `<reliability><kind>`.
    pub reliability: Option<Reliability>,
    /// `<durability><kind>`.
    pub durability: Option<Durability>,
    /// `<historyQos>` / `<history>`.
    pub history: Option<History>,
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
}

fn parse(xml: &str) -> Result<Document<'_>, XmlError> {
    Document::parse(xml).map_err(|e| XmlError::Malformed(e.to_string()))
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

/// Parses a participant representation; returns its RTPS name if given.
pub fn parse_participant(xml: &str) -> Result<Option<String>, XmlError> {
    let doc = parse(xml)?;
    let p = find(&doc, "participant")
        .or_else(|| find(&doc, "domain_participant"))
        .ok_or(XmlError::Missing("<participant>"))?;
    Ok(child(p, "rtps")
        .and_then(|r| text(r, "name"))
        .or_else(|| p.attribute("name").map(str::to_string)))
}

/// Parses a topic representation.
pub fn parse_topic(xml: &str) -> Result<TopicDesc, XmlError> {
    let doc = parse(xml)?;
    let t = find(&doc, "topic").ok_or(XmlError::Missing("<topic>"))?;
    parse_topic_node(t)
}

/// Parses a `data_writer` or `data_reader` representation.
pub fn parse_endpoint(xml: &str, element: &'static str) -> Result<EndpointDesc, XmlError> {
    let doc = parse(xml)?;
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
        let inner = parse_qos(q)?;
        qos.reliability = inner.reliability.or(qos.reliability);
        qos.durability = inner.durability.or(qos.durability);
        qos.history = inner.history.or(qos.history);
    }
    Ok(EndpointDesc {
        topic,
        topic_ref,
        topic_id: None,
        qos,
    })
}

#[cfg(test)]
mod tests {
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
