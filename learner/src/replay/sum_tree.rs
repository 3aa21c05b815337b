//! A sum tree over priorities: O(log n) update and proportional lookup.

use serde::{Deserialize, Serialize};

/// Leaves hold priorities; each inner node holds the sum of its children.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SumTree {
    leaves: usize,
    /// Heap layout: node 1 is the root, node i has children 2i and 2i + 1; leaf j is node
    /// `leaves + j`. Node 0 is unused.
    nodes: Vec<f64>,
}

impl SumTree {
    pub fn new(capacity: usize) -> Self {
        let leaves = capacity.max(1).next_power_of_two();
        Self { leaves, nodes: vec![0.0; 2 * leaves] }
    }

    pub fn total(&self) -> f64 {
        self.nodes[1]
    }

    pub fn get(&self, index: usize) -> f64 {
        self.nodes[self.leaves + index]
    }

    pub fn set(&mut self, index: usize, priority: f64) {
        let mut node = self.leaves + index;
        self.nodes[node] = priority;
        while node > 1 {
            node /= 2;
            self.nodes[node] = self.nodes[2 * node] + self.nodes[2 * node + 1];
        }
    }

    /// The leaf where the running sum of priorities first exceeds `mass` (0 ≤ mass < total).
    pub fn find(&self, mut mass: f64) -> usize {
        let mut node = 1;
        while node < self.leaves {
            let left = 2 * node;
            if mass < self.nodes[left] || self.nodes[left + 1] <= 0.0 {
                node = left;
            } else {
                mass -= self.nodes[left];
                node = left + 1;
            }
        }
        node - self.leaves
    }

    pub fn memory_bytes(&self) -> usize {
        self.nodes.capacity() * size_of::<f64>()
    }

    /// Checks a tree read from a file against the `capacity` it serves: its shape, and every
    /// leaf finite and non-negative (nothing stored beyond `capacity`). The inner sums are
    /// then recomputed from the leaves rather than trusted.
    pub fn check_snapshot(&mut self, capacity: usize) -> Result<(), String> {
        let leaves = capacity.max(1).next_power_of_two();
        if self.leaves != leaves || self.nodes.len() != 2 * leaves {
            return Err(format!(
                "sampler tree has {} leaves and {} nodes, a replay of {capacity} slots needs {leaves} and {}",
                self.leaves,
                self.nodes.len(),
                2 * leaves
            ));
        }
        for (index, &priority) in self.nodes[leaves..].iter().enumerate() {
            let allowed = if index < capacity { priority.is_finite() && priority >= 0.0 } else { priority == 0.0 };
            if !allowed {
                return Err(format!("sampler priority {priority} at slot {index}"));
            }
        }
        for node in (1..leaves).rev() {
            self.nodes[node] = self.nodes[2 * node] + self.nodes[2 * node + 1];
        }
        if !self.total().is_finite() {
            return Err(format!("sampler priorities sum to {}", self.total()));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn find_follows_cumulative_mass() {
        let mut tree = SumTree::new(5);
        for (i, p) in [1.0, 0.0, 3.0, 2.0, 4.0].into_iter().enumerate() {
            tree.set(i, p);
        }
        assert_eq!(tree.total(), 10.0);
        assert_eq!(tree.find(0.0), 0);
        assert_eq!(tree.find(0.999), 0);
        assert_eq!(tree.find(1.0), 2);
        assert_eq!(tree.find(3.999), 2);
        assert_eq!(tree.find(4.0), 3);
        assert_eq!(tree.find(9.999), 4);
        tree.set(4, 0.0);
        assert_eq!(tree.total(), 6.0);
    }
}
