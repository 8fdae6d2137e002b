//! The references file (`-r`): a Fast DDS XML profiles document whose `profile_name`
//! attributes are the labels clients use in REPRESENTATION_BY_REFERENCE, as with eProsima's
//! MicroXRCEAgent. A reference resolves to the profile's XML, which then goes through the
//! same parsing as an XML representation.

use std::collections::HashMap;

/// Profiles by name, with the element kind they describe.
#[derive(Debug, Clone, Default)]
pub struct References {
    profiles: HashMap<String, Profile>,
    types: crate::types::TypeSet,
}

#[derive(Debug, Clone)]
struct Profile {
    element: String,
    xml: String,
}

/// Why a references file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ReferencesError {
    /// Reading the file failed.
    #[error("reading {path}: {error}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        error: std::io::Error,
    },
    /// The file is not well-formed XML.
    #[error("parsing {path}: {error}")]
    Xml {
        /// The file.
        path: String,
        /// What the parser said.
        error: String,
    },
    /// A `<types>` section could not be used.
    #[error("{path}: {error}")]
    Types {
        /// The file.
        path: String,
        /// What is wrong with the types.
        error: crate::types::TypeError,
    },
    /// Two profiles share a name.
    #[error("{path}: profile_name {name:?} appears twice")]
    Duplicate {
        /// The file.
        path: String,
        /// The name.
        name: String,
    },
}

impl References {
    /// Loads a profiles file.
    pub fn load(path: &std::path::Path) -> Result<Self, ReferencesError> {
        let text = std::fs::read_to_string(path).map_err(|error| ReferencesError::Io {
            path: path.display().to_string(),
            error,
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses a profiles document (`origin` names it in errors).
    pub fn parse(text: &str, origin: &str) -> Result<Self, ReferencesError> {
        let doc = roxmltree::Document::parse(text).map_err(|e| ReferencesError::Xml {
            path: origin.into(),
            error: e.to_string(),
        })?;
        let mut profiles = HashMap::new();
        for node in doc.descendants().filter(|n| n.is_element()) {
            let Some(name) = node.attribute("profile_name") else {
                continue;
            };
            let profile = Profile {
                element: node.tag_name().name().to_string(),
                xml: text[node.range()].to_string(),
            };
            if profiles.insert(name.to_string(), profile).is_some() {
                return Err(ReferencesError::Duplicate {
                    path: origin.into(),
                    name: name.into(),
                });
            }
        }
        let types = crate::types::TypeSet::parse(text).map_err(|error| ReferencesError::Types {
            path: origin.into(),
            error,
        })?;
        Ok(References { profiles, types })
    }

    /// The types the file's `<types>` sections define (keyed topics and content filters of
    /// every client can use them).
    pub fn types(&self) -> &crate::types::TypeSet {
        &self.types
    }

    /// Number of profiles.
    pub fn len(&self) -> usize {
        self.profiles.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.profiles.is_empty()
    }

    /// The XML of the profile `reference` describing an `element` (e.g. `data_writer`).
    /// `Library::Profile` references (the spec's form) also match a profile named `Profile`.
    pub fn resolve(&self, reference: &str, element: &str) -> Result<&str, String> {
        let profile = self
            .profiles
            .get(reference)
            .or_else(|| {
                reference
                    .rsplit("::")
                    .next()
                    .and_then(|last| self.profiles.get(last))
            })
            .ok_or_else(|| format!("reference {reference:?} is not in the references file"))?;
        if profile.element != element {
            return Err(format!(
                "reference {reference:?} is a {}, not a {element}",
                profile.element
            ));
        }
        Ok(&profile.xml)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::xml;

    const REFS: &str = r#"<?xml version="1.0"?>
<dds>
<profiles>
  <participant profile_name="default_xrce_participant">
    <rtps><name>default_xrce_participant</name></rtps>
  </participant>
  <data_writer profile_name="shapetype_data_writer">
    <topic><kind>WITH_KEY</kind><name>Square</name><dataType>ShapeType</dataType></topic>
    <qos><reliability><kind>RELIABLE</kind></reliability></qos>
  </data_writer>
  <topic profile_name="shapetype_topic">
    <kind>WITH_KEY</kind><name>Square</name><dataType>ShapeType</dataType>
  </topic>
</profiles>
<types>
  <type><struct name="ShapeType">
    <member name="color" type="string" key="true"/><member name="x" type="int32"/>
  </struct></type>
</types>
</dds>"#;

    #[test]
    fn resolves_profiles_by_name_and_kind() {
        let r = References::parse(REFS, "test").expect("parse");
        assert_eq!(r.len(), 3);
        let w = r
            .resolve("shapetype_data_writer", "data_writer")
            .expect("writer");
        let desc = xml::parse_endpoint(w, "data_writer").expect("writer XML");
        assert_eq!(desc.topic.map(|t| t.name), Some("Square".into()));
        assert_eq!(
            desc.qos.reliability,
            Some(crate::backend::policies::Reliability::Reliable)
        );
        let t = r
            .resolve("Lib::shapetype_topic", "topic")
            .expect("library form");
        assert_eq!(xml::parse_topic(t).expect("topic").type_name, "ShapeType");
        assert!(r.resolve("shapetype_topic", "data_reader").is_err());
        assert!(r.resolve("nope", "topic").is_err());
        assert!(r.types().get("ShapeType").is_some_and(|t| t.is_keyed()));
    }

    #[test]
    fn bad_files_are_reported() {
        assert!(matches!(
            References::parse("<profiles>", "x"),
            Err(ReferencesError::Xml { .. })
        ));
        let dup = r#"<profiles><topic profile_name="a"/><topic profile_name="a"/></profiles>"#;
        assert!(matches!(
            References::parse(dup, "x"),
            Err(ReferencesError::Duplicate { .. })
        ));
        let bad_type = r#"<dds><types><struct name="A"><member name="b" type="nonBasic" nonBasicTypeName="B"/></struct></types></dds>"#;
        assert!(matches!(
            References::parse(bad_type, "x"),
            Err(ReferencesError::Types { .. })
        ));
    }
}
