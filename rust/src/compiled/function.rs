//! Loading a CasADi-generated shared library: the symbols of one function, the checks of its
//! inputs' and outputs' shapes (dense, of the sizes the model's dimensions say), and its calls.

use std::sync::Mutex;

use libloading::Library;

use crate::error::{Error, Result};

type EvalFn =
    unsafe extern "C" fn(*const *const f64, *mut *mut f64, *mut i64, *mut f64, i32) -> i32;
type WorkFn = unsafe extern "C" fn(*mut i64, *mut i64, *mut i64, *mut i64) -> i32;
type CountFn = unsafe extern "C" fn() -> i64;
type SparsityFn = unsafe extern "C" fn(i64) -> *const i64;
type RefFn = unsafe extern "C" fn();
type CheckoutFn = unsafe extern "C" fn() -> i32;
type ReleaseFn = unsafe extern "C" fn(i32);
type SizeFn = unsafe extern "C" fn() -> i32;

/// One generated function: its entry points (valid while the library that holds them is loaded)
/// and its work sizes.
pub(super) struct Function {
    name: String,
    eval: EvalFn,
    checkout: CheckoutFn,
    release: ReleaseFn,
    decref: RefFn,
    /// Work sizes: pointers to inputs and outputs, integer and real work.
    pub(super) sizes: [usize; 4],
    /// A function with memory (a rootfinder, say) runs one call at a time.
    lock: Option<Mutex<()>>,
}

fn symbol<T: Copy>(lib: &Library, name: &str) -> Result<T> {
    // SAFETY: the symbol's type is CasADi's documented C signature for generated code; the
    // caller keeps the library loaded while it uses the pointer.
    unsafe { lib.get::<T>(name.as_bytes()).map(|s| *s) }.map_err(|e| {
        Error::invalid(
            "model",
            format!("the compiled model has no symbol {name}: {e}"),
        )
    })
}

impl Function {
    /// The function `name` of `lib`, checked: one dense input of `n_in` values and dense outputs
    /// of the `outputs` sizes.
    pub(super) fn load(lib: &Library, name: &str, n_in: usize, outputs: &[usize]) -> Result<Self> {
        let s = |suffix: &str| format!("{name}{suffix}");
        let count_in: CountFn = symbol(lib, &s("_n_in"))?;
        let count_out: CountFn = symbol(lib, &s("_n_out"))?;
        let sparsity_in: SparsityFn = symbol(lib, &s("_sparsity_in"))?;
        let sparsity_out: SparsityFn = symbol(lib, &s("_sparsity_out"))?;
        let work: WorkFn = symbol(lib, &s("_work"))?;
        let incref: RefFn = symbol(lib, &s("_incref"))?;
        // SAFETY: CasADi's generated query functions take no pointers (or write four sizes).
        let (ins, outs) = unsafe { (count_in(), count_out()) };
        if ins != 1 || outs != outputs.len() as i64 {
            return Err(Error::invalid(
                "model",
                format!(
                    "{name} has {ins} inputs and {outs} outputs, expected 1 and {}",
                    outputs.len()
                ),
            ));
        }
        check_dense(name, "input", unsafe { sparsity_in(0) }, n_in)?;
        for (i, &size) in outputs.iter().enumerate() {
            check_dense(name, "output", unsafe { sparsity_out(i as i64) }, size)?;
        }
        let mut sz = [0i64; 4];
        let [a, r, iw, w] = &mut sz;
        if unsafe { work(a, r, iw, w) } != 0 || sz.iter().any(|&v| v < 0) {
            return Err(Error::invalid(
                "model",
                format!("{name}: its work sizes are unreadable"),
            ));
        }
        let sizes = sz.map(|v| v as usize);
        if sizes[0] < 1 || sizes[1] < outputs.len() {
            return Err(Error::invalid(
                "model",
                format!("{name}: its work sizes are too small"),
            ));
        }
        let has_memory = symbol::<RefFn>(lib, &s("_alloc_mem")).is_ok();
        unsafe { incref() };
        Ok(Self {
            name: name.to_string(),
            eval: symbol(lib, name)?,
            checkout: symbol(lib, &s("_checkout"))?,
            release: symbol(lib, &s("_release"))?,
            decref: symbol(lib, &s("_decref"))?,
            sizes,
            lock: has_memory.then(|| Mutex::new(())),
        })
    }

    pub(super) fn name(&self) -> &str {
        &self.name
    }

    /// Evaluates at the input `arg` into the output slices `res` (their sizes checked at load),
    /// with the work buffers of `work` (sized for this function by [`Work::fit`]). Returns false
    /// if the generated code reports a failure.
    pub(super) fn call(&self, arg: &[f64], res: &mut [&mut [f64]], work: &mut Work) -> bool {
        let Work { args, outs, iw, w } = work;
        debug_assert!(args.len() >= self.sizes[0] && outs.len() >= self.sizes[1]);
        debug_assert!(iw.len() >= self.sizes[2] && w.len() >= self.sizes[3]);
        args.fill(0);
        outs.fill(0);
        args[0] = arg.as_ptr() as usize;
        for (o, r) in outs.iter_mut().zip(res.iter_mut()) {
            *o = if r.is_empty() {
                0
            } else {
                r.as_mut_ptr() as usize
            };
        }
        let _guard = self
            .lock
            .as_ref()
            .map(|l| l.lock().unwrap_or_else(|e| e.into_inner()));
        // SAFETY: the pointers (kept as addresses, so that the work buffers stay `Send`) cover
        // the sizes the library reported and checked at load; the library stays loaded while
        // `self` exists (see `CompiledLibrary`).
        unsafe {
            let mem = (self.checkout)();
            let status = (self.eval)(
                args.as_ptr() as *const *const f64,
                outs.as_mut_ptr() as *mut *mut f64,
                iw.as_mut_ptr(),
                w.as_mut_ptr(),
                mem,
            );
            (self.release)(mem);
            status == 0
        }
    }
}

/// The work buffers of calls: pointers to the inputs and outputs (as addresses), integer and
/// real work; one set per evaluating model, sized for every function it calls.
#[derive(Debug, Clone, Default)]
pub(super) struct Work {
    args: Vec<usize>,
    outs: Vec<usize>,
    iw: Vec<i64>,
    w: Vec<f64>,
}

impl Work {
    /// Grows the buffers to fit `f`'s work sizes.
    pub(super) fn fit(&mut self, f: &Function) {
        let [a, r, iw, w] = f.sizes;
        for (v, len) in [(&mut self.args, a), (&mut self.outs, r)] {
            if v.len() < len {
                v.resize(len, 0);
            }
        }
        if self.iw.len() < iw.max(1) {
            self.iw.resize(iw.max(1), 0);
        }
        if self.w.len() < w.max(1) {
            self.w.resize(w.max(1), 0.0);
        }
    }
}

impl Drop for Function {
    fn drop(&mut self) {
        // SAFETY: paired with the incref in `load`; the library is unloaded after its functions.
        unsafe { (self.decref)() }
    }
}

/// Fails unless `sp` (CasADi's compressed-column sparsity: rows, columns, column offsets, row
/// indices; or rows, columns, 1 for a dense matrix, since the first offset of the full form is 0)
/// is a dense pattern of `size` entries.
fn check_dense(name: &str, what: &str, sp: *const i64, size: usize) -> Result<()> {
    if sp.is_null() {
        return Err(Error::invalid(
            "model",
            format!("{name}: no sparsity for an {what}"),
        ));
    }
    // SAFETY: a non-null pattern starts with its row and column counts, then ncol + 1 offsets.
    let (rows, cols) = unsafe { (*sp, *sp.add(1)) };
    if rows < 0 || cols < 0 || rows.saturating_mul(cols) != size as i64 {
        return Err(Error::invalid(
            "model",
            format!("{name}: an {what} is {rows}×{cols}, expected {size} values"),
        ));
    }
    // SAFETY: the third entry exists in both forms; the full form has ncol + 1 offsets.
    let compact_dense = unsafe { *sp.add(2) } == 1;
    let nnz = if compact_dense {
        size as i64
    } else {
        unsafe { *sp.add(2 + cols as usize) }
    };
    if nnz != size as i64 {
        return Err(Error::invalid(
            "model",
            format!("{name}: an {what} is not dense"),
        ));
    }
    Ok(())
}

/// A loaded library with the model's stage and prediction functions, for dimensions (n, m, p).
pub struct CompiledLibrary {
    pub(super) stage: Function,
    pub(super) predict: Function,
    pub(super) dims: (usize, usize, usize),
    path: String,
    // Declared last: dropped after the functions, whose pointers point into it.
    _lib: Library,
}

impl std::fmt::Debug for CompiledLibrary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "CompiledLibrary({:?}, dims {:?})", self.path, self.dims)
    }
}

impl CompiledLibrary {
    /// Loads the library at `path` and its functions `stage` (outputs f, ∂f/∂dᵀ, h, ∂h/∂dᵀ) and
    /// `predict` (output f), all of one point d of n + m values, checking every shape.
    pub fn load(
        path: &str,
        stage: &str,
        predict: &str,
        dims: (usize, usize, usize),
    ) -> Result<Self> {
        // SAFETY: loading runs the library's initialisers; gpmhe loads only libraries it
        // generated from CasADi code and verified by checksum (see gpmhe.models.compiled).
        let lib = unsafe { Library::new(path) }.map_err(|e| {
            Error::invalid(
                "model",
                format!("cannot load the compiled model {path}: {e}"),
            )
        })?;
        let int_size: SizeFn = symbol(&lib, "gpmhe_model_casadi_int_size")?;
        let real_size: SizeFn = symbol(&lib, "gpmhe_model_casadi_real_size")?;
        if unsafe { (int_size(), real_size()) } != (8, 8) {
            return Err(Error::invalid(
                "model",
                "the compiled model's casadi_int and casadi_real must be 64-bit",
            ));
        }
        let (n, m, p) = dims;
        let nd = n + m;
        let stage = Function::load(&lib, stage, nd, &[n, n * nd, p, p * nd])?;
        let predict = Function::load(&lib, predict, nd, &[n])?;
        Ok(Self {
            stage,
            predict,
            dims,
            path: path.to_string(),
            _lib: lib,
        })
    }

    pub fn path(&self) -> &str {
        &self.path
    }

    pub fn dims(&self) -> (usize, usize, usize) {
        self.dims
    }
}
