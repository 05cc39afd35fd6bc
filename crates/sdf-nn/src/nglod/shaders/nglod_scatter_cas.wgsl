// The grid gradients' scatter of nglod_train.wgsl for adapters without float atomics: the
// gradients' bit patterns in atomic<u32>.
@group(0) @binding(5) var<storage, read_write> grads: array<atomic<u32>>;

// Float add without float atomics: retry a compare-exchange on the bit pattern until no other
// invocation changed the value in between.
fn grad_add(i: u32, x: f32) {
    var old = atomicLoad(&grads[i]);
    loop {
        let r = atomicCompareExchangeWeak(&grads[i], old, bitcast<u32>(bitcast<f32>(old) + x));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}
