//! Turns: keys waiting for their turn at a shared resource, served first come, first
//! served, each at most once in the line.
//!
//! The worker keeps the readers that have samples to send to a front-end in one of these,
//! and those held back while that front-end's queue is full in another. A hash set in their
//! place served them in hash order, the same order every pass: a reader with a steady flood
//! of samples that came first in that order refilled the front-end's queue on every pass,
//! and the reads of the other clients of that front-end waited for the flood to end.

use std::collections::{HashSet, VecDeque};
use std::hash::Hash;

/// A line of distinct keys in arrival order.
#[derive(Debug, Clone)]
pub struct Turns<K> {
    order: VecDeque<K>,
    waiting: HashSet<K>,
}

impl<K> Default for Turns<K> {
    fn default() -> Self {
        Turns {
            order: VecDeque::new(),
            waiting: HashSet::new(),
        }
    }
}

impl<K: Copy + Eq + Hash> Turns<K> {
    /// An empty line.
    pub fn new() -> Self {
        Self::default()
    }

    /// Puts `key` at the end of the line, unless it is in it already (it keeps its place).
    pub fn push(&mut self, key: K) {
        if self.waiting.insert(key) {
            self.order.push_back(key);
        }
    }

    /// Takes `key` out of the line, wherever it is.
    pub fn remove(&mut self, key: &K) {
        if self.waiting.remove(key) {
            self.order.retain(|k| k != key);
        }
    }

    /// Keeps only the keys `keep` says yes to, in their order.
    pub fn retain(&mut self, mut keep: impl FnMut(&K) -> bool) {
        self.order.retain(|k| keep(k));
        self.waiting.retain(|k| keep(k));
    }

    /// Empties the line, first come first.
    pub fn take_all(&mut self) -> Vec<K> {
        self.waiting.clear();
        self.order.drain(..).collect()
    }

    /// Moves every key of `other` to the end of this line, in `other`'s order.
    pub fn append(&mut self, other: &mut Turns<K>) {
        for k in other.take_all() {
            self.push(k);
        }
    }

    /// The keys in the line, first come first.
    pub fn iter(&self) -> impl Iterator<Item = &K> {
        self.order.iter()
    }

    /// Whether `key` is in the line.
    pub fn contains(&self, key: &K) -> bool {
        self.waiting.contains(key)
    }

    /// Whether the line is empty.
    pub fn is_empty(&self) -> bool {
        self.order.is_empty()
    }

    /// Keys in the line.
    pub fn len(&self) -> usize {
        self.order.len()
    }

    /// Empties the line.
    pub fn clear(&mut self) {
        self.order.clear();
        self.waiting.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_come_out_in_arrival_order_once_each() {
        let mut t = Turns::new();
        for k in [7, 3, 7, 9, 3, 1] {
            t.push(k);
        }
        assert_eq!(t.len(), 4);
        assert!(t.contains(&9) && !t.contains(&2));
        assert_eq!(t.take_all(), [7, 3, 9, 1]);
        assert!(t.is_empty());
        // Taken out, a key queues again at the end.
        t.push(3);
        t.push(7);
        assert_eq!(t.take_all(), [3, 7]);
    }

    #[test]
    fn remove_retain_and_append_keep_the_order_of_the_rest() {
        let mut t = Turns::new();
        for k in 0..10 {
            t.push(k);
        }
        t.remove(&4);
        t.remove(&42);
        t.retain(|k| k % 3 != 0);
        let mut later = Turns::new();
        later.push(5);
        later.push(11);
        later.push(0);
        t.append(&mut later);
        assert!(later.is_empty());
        // 5 was already in the line and keeps its place; 0 had been dropped and comes last.
        assert_eq!(t.take_all(), [1, 2, 5, 7, 8, 11, 0]);
        t.push(1);
        t.clear();
        assert!(t.is_empty());
        t.push(1);
        assert_eq!(t.take_all(), [1]);
    }
}
