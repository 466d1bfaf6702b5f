//! Containers that hold themselves. A pickle stream can append a list to itself (directly, or
//! through any chain of tuples, calls and dicts); reference counting never frees such a value,
//! so every checkpoint that made one would leak it (the `pickle` fuzz target ran out of memory
//! after 7.5 million of them). State dicts never hold themselves: the parser refuses such a
//! stream, and empties what it made so that it is freed.

use std::collections::HashMap;

use super::pickle::Value;

/// Whether any value reachable from `roots` holds itself. If one does, every list and dict
/// reachable from them is emptied, which breaks every cycle (they are the only values a stream
/// can change after making them, so every cycle passes through one). One depth-first walk with
/// an explicit stack: linear in the values made, however deep they nest.
pub(super) fn break_cycles<'a>(roots: impl IntoIterator<Item = &'a Value>) -> bool {
    // Values seen: true while on the current path, false once every child has been walked.
    let mut on_path: HashMap<*const (), bool> = HashMap::new();
    let mut containers: Vec<Value> = vec![];
    let mut cycle = false;
    for root in roots {
        let Some(id) = root.node() else { continue };
        if on_path.contains_key(&id) {
            continue;
        }
        on_path.insert(id, true);
        containers.push(root.clone());
        let mut path: Vec<(Value, usize)> = vec![(root.clone(), 0)];
        while let Some(top) = path.last_mut() {
            let next = top.0.child(top.1);
            top.1 += 1;
            let Some(child) = next else {
                let (done, _) = path.pop().expect("the path's last value");
                on_path.insert(done.node().expect("only values holding others are walked"), false);
                continue;
            };
            let Some(id) = child.node() else { continue };
            match on_path.get(&id) {
                Some(true) => cycle = true,
                Some(false) => {}
                None => {
                    on_path.insert(id, true);
                    containers.push(child.clone());
                    path.push((child, 0));
                }
            }
        }
    }
    if cycle {
        containers.iter().for_each(Value::empty);
    }
    cycle
}

#[cfg(test)]
mod tests {
    use super::super::pickle::parse;
    use super::*;

    /// A list that holds itself through a tuple: found, and freed once emptied.
    #[test]
    fn a_list_holding_itself_is_found_and_freed() {
        // ] q1 h1 h1 \x85 a . : l = []; l.append((l,)); return l
        let stream = b"]q\x01h\x01\x85a.";
        assert!(matches!(parse(stream), Err(super::super::pickle::PickleError::Cycle)));
        let l = Value::List(Default::default());
        let Value::List(rc) = &l else { unreachable!() };
        rc.borrow_mut().push(Value::Tuple(std::rc::Rc::from([l.clone()])));
        let weak = std::rc::Rc::downgrade(rc);
        assert!(break_cycles([&l]));
        drop(l);
        assert!(weak.upgrade().is_none(), "the list outlived its last owner");
    }

    /// Shared values that form no cycle (one tuple twice in a list, a dict reached twice) are
    /// not cycles, and are left as they are.
    #[test]
    fn shared_values_are_not_cycles() {
        // ] K1 \x85 q1 a h1 a . : t = (1,); [t, t]
        let v = parse(b"]K\x01\x85q\x01ah\x01a.").unwrap();
        assert!(!break_cycles([&v]));
        assert_eq!(v.items().unwrap().len(), 2);
    }
}
