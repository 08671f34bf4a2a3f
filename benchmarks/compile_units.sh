#!/usr/bin/env bash
# Issue 21's compile measurements as one unit inside one lease of a one-GPU machine (started once as its own
# process session, then polled: experiments/lease.sh), carrying .whl-site (the packed wheels; or .whl where it fits):
#
#   bash benchmarks/compile_units.sh UNIT [WAIT_S]
#
# UNIT is one of
#   flags    the 4-arm ant sweep (`--env ant --arms model-free mbmf cd-k5 cd`, 3 seeds) compiled cold (an empty
#            persistent cache each time) by benchmarks.compile_time: with XLA's defaults; with Triton's GEMM fusions
#            off (XLA_FLAGS=--xla_gpu_enable_triton_gemm=false: cuBLAS alone, far fewer autotuning candidates);
#            and one program after another (CDJAX_COMPILE_WORKERS=1: each program's compile alone, no sharing of
#            CPU cores or the autotuner). Then what Triton's GEMMs off costs at run time: the CD arm alone, cold,
#            3 seeds, 8M env steps per run, with and without the flag (the training line's env steps/s).
#   lowered  the same sweep's programs lowered, not compiled (benchmarks.compile_time --lower-only): their sizes
#            on this host, to set beside the compile times.
#   speed    the 4-arm sweep cold in cdjax's own `fast` compile mode (CDJAX_COMPILE_MODE=fast: Triton's GEMMs off,
#            per program), then what that costs in steady state, case by case: the compare suite (Brax PPO,
#            model-free, Mb-Mf, CD on the paper's schedule; ant, 4096 envs, the matched Spec) in two
#            processes, XLA's defaults and XLA_FLAGS=--xla_gpu_enable_triton_gemm=false (the suite jits its own
#            programs, so the flag, not cdjax's per-program mode, reaches all of them, Brax's too).
#   accept   issue 21's acceptance figures in one lease (about 12 minutes on an H200 as measured in parts before;
#            ask for nvidia-h100-x1 to set them beside 2026-11-24-h100-compare): the compare suite (Brax PPO,
#            model-free, Mb-Mf, CD on the paper's schedule; ant, 4096 envs, the matched Spec) in one process with a
#            profile of one update per cdjax case (--trace: what remains); then, in a process of its own so that
#            the compare suite's budget cannot skip it, the seeds suite at 10 vmapped seeds of 256 envs for Mb-Mf and
#            the paper's CD (the 10-seed ratio, profiled); then the 4-arm ant sweep compiled cold with XLA's defaults
#            (the README's compile figure). Each part is stopped by `timeout` so the unit ends inside 840 s.
#            ACCEPT_CASES (default "brax-ppo model-free mbmf cd-paper") and ACCEPT_BUDGET (default 330 s) set the
#            compare part's cases and budget: with `ceiling collect` too, its table splits each update into physics,
#            rollout and SGD.
#   hlo      what the largest kernels of the model arms compute and cost (about 8 minutes): the compare suite's Mb-Mf,
#            Mb-Mf with `benchmarks.variants no-loss-metrics` (the losses' diagnostics dropped, gradients unchanged),
#            paper-CD and paper-CD with `benchmarks.variants bias-sum` (the chain's bias gradients as separate sums)
#            cases, each in a process of its own with XLA's optimised HLO of its update dumped (XLA_FLAGS
#            --xla_dump_to, modules jit_update) and one update profiled (--trace); then `benchmarks.hlo_fusions
#            --profile` on each: every case's 8 costliest fusion kernels with their time, launch shape (blocks x
#            threads), fused computation and JAX source lines (fusions-CASE.log; hlo.tar.gz holds the optimised HLO
#            text), and `--loops`: the kernels each loop body launches per pass, by group (loops-CASE.log).
#            On 2026-11-25 (H100) it found a one-block fusion of the losses' backward with the reward MSE's sum
#            (67 ms of Mb-Mf's 0.528 s per update; the SGD now reduces its diagnostics once per update) and kept the
#            chain's one-product weight gradients (bias-sum: paper-CD 0.839 s against 0.805 s).
#   hlo-seeds  `hlo` for the seeds suite's programs (about 5 minutes): Mb-Mf and paper-CD at 10 vmapped seeds of 256
#            envs, each in a process of its own with XLA's optimised HLO of its program dumped (module jit_run) and one
#            update profiled, then `benchmarks.hlo_fusions --profile` and `--loops` on each. On 2026-11-27 (H100)
#            Mb-Mf's costliest 10-seed kernel was a 3-block reduction, `input_add_multiply_negate_reduce_select...`,
#            18.7 ms of 0.418 s per update, absent from the single-seed program
#            (benchmarks/results/2026-11-27-h100-accept/).
#            HLO_CASES (default "mbmf mbmf-nometrics cd-paper cd-paper-biassum") names the `hlo` unit's cases: any
#            compare case, with -nometrics or -biassum for the variant; HLO_TOP (default 8) how many of each profile's
#            costliest fusion kernels `hlo` and `hlo-seeds` trace to their source.
#   cublaslt XLA's GEMMs through the legacy cuBLAS API instead of cuBLASLt (--xla_gpu_enable_cublaslt=false), in
#            processes of their own (about 12 minutes; flag_ab): the compare suite (Brax PPO, model-free, Mb-Mf,
#            paper-CD), then the seeds suite's Mb-Mf and paper-CD at 10 vmapped seeds of 256 envs, each with and without
#            the flag. At 10
#            seeds XLA transposes each batched weight-gradient product's [10, 672, 256] input to [10, 256, 672]
#            before its cuBLASLt call, 14 transposes per SGD step in Mb-Mf
#            (benchmarks/results/2026-11-27-h100-hlo-seeds/); the single-seed program calls cuBLAS with the
#            operand transposed in place. Whether the legacy API takes the batched operands as they are.
#   ab       the working tree against an earlier revision in one lease (about 10 minutes at the default): AB_RUN
#            (default the seeds suite's Mb-Mf and paper-CD at 10 vmapped seeds of 256 envs, `benchmarks.run ...`) four
#            times in processes of their own, ABBA: here, then in runs/ab-base/ (the cdjax package and benchmark modules
#            of the revision, written here by `bash benchmarks/ab_base.sh REV`; carry runs/ab-base beside .whl-site),
#            each stopped after AB_LIMIT seconds (default 200). For a change no variant can switch off.
#   chain    the consistency chain's CUDA kernels (cdjax/kernels/chain.cu) against XLA's fused chain, about 4
#            minutes: first `--compare-modes` (the cluster kernels' outputs against the plain kernels', output by
#            output), then `python -m benchmarks.chain_kernel --cluster`, the gradients' accuracy (alone and
#            vmapped) and the time of the chain's value and gradient for XLA's chain, the plain kernels and the cluster
#            kernels
#            (CDJAX_CHAIN_KERNEL=cluster: 4 blocks per 16 rows, the weights in shared memory). On 2026-11-27 (H100)
#            both kinds were correct and slower than XLA's chain at 512 rows (cluster 2.40 ms, plain 2.18, XLA 1.44)
#            (benchmarks/results/2026-11-27-h100-chain-cluster/).
#   chain-e2e  what the kernels do to whole updates, about 10 minutes: the seeds suite's Mb-Mf and paper-CD at 10
#            vmapped seeds of 256 envs, then the compare suite's Mb-Mf and paper-CD (ant, 4096 envs), each in a
#            process with XLA's chain and one with CDJAX_CHAIN_KERNEL=${CHAIN_MODE:-cluster} (1: the plain kernels).
#            On 2026-11-27 (H100) the cluster kernels: paper-CD 0.6802 against 0.6727 s/update at 10 seeds, 0.9401
#            against 0.7364 at 4096 envs (benchmarks/results/2026-11-27-h100-chain-cluster/).
#   cmdbuf   XLA's while loops and conditionals inside CUDA graphs (--xla_gpu_enable_command_buffer=... plus WHILE and
#            CONDITIONAL: no host round trip for a loop's predicate, no launch per pass), as `cublaslt` does its flag
#            (flag_ab). On 2026-11-27 (H100) 0.7-3.2% slower in every case, not adopted
#            (benchmarks/results/2026-11-27-h100-cmdbuf/).
#   pdl      programmatic dependent launch (--xla_gpu_enable_pdl=true: on Hopper a kernel may start while the one it
#            depends on finishes, its prologue overlapping the other's tail), as `cublaslt` does its flag (flag_ab). The
#            SGD step of paper-CD is ~480 small dependent kernels busy 95% of its span, 4-8 µs each at 512 rows
#            (benchmarks/results/2026-11-28-h100-accept/): whether the overlap shortens the chain.
#   regions  XLA's copy insertion with region analysis for cdjax's programs (CDJAX_XLA_OPTIONS=
#            xla_gpu_copy_insertion_use_region_analysis=true, per program: Brax PPO stays at XLA's own), about 10
#            minutes: the compare suite (Brax PPO, model-free, Mb-Mf, paper-CD) and the seeds suite's Mb-Mf and paper-CD
#            at 10 vmapped seeds of 256 envs, each in a process without and one with it. In the model-free update of
#            2026-11-27 (benchmarks/results/2026-11-27-h100-hlo-model-free/loops-model-free.log) about 16,000 of the
#            120,000 kernels per update are copies, most of them of loop-carried values in MJX's loop bodies: 16 a
#            physics substep (400 a update), 6 a pass of a 9-kernel loop (1,600 passes; MJX's line search). On this
#            project's CPU the option's CPU twin took the line search body's copies from 8 to 3 (the ant's step, 8
#            envs). Whether the GPU's copies go too, and what that is worth per update (at about 3 us a kernel).
#            On 2026-11-27 (H100) model-free and Mb-Mf 3.3% slower with it, paper-CD 0.6% faster, at 10 seeds Mb-Mf
#            1.6% faster and paper-CD 4.2% slower: not adopted (benchmarks/results/2026-11-27-h100-regions/).
#   regions-hlo  the optimised HLO of the compare suite's ${HLO_CASES:-model-free} update with and without the option,
#            one update profiled each (`dumped_case`, about 3 minutes): the kernels, copies among them, of each loop
#            body (loops-CASE.log against loops-CASE-regions.log).
#   determinism-cd  the `determinism` unit's last part alone (its lease cut it): the compare suite's Mb-Mf and paper-CD
#            under XLA_FLAGS=--xla_gpu_deterministic_ops=true, one process, about 2 minutes. On 2026-11-27 (H100)
#            0.7245 and 1.0516 s per update, 1.80x and 1.66x cdjax's defaults on that machine
#            (benchmarks/results/2026-11-27-h100-determinism/).
#   topn     the cost model's top N GEMM tilings (TOPN, default "4 8"; cdjax keeps 2) process-wide, about 10 minutes:
#            the seeds suite's Mb-Mf and paper-CD at 10 vmapped seeds of 256 envs at cdjax's default and at each N,
#            and the cold 4-arm ant sweep at each N. XLA's own search made paper-CD 10% faster at 10 seeds and the cold
#            sweep about a quarter longer (benchmarks/results/2026-11-27-h100-tuned/). On 2026-11-27 (H100) top 4 and 8
#            made paper-CD 2.6% and 5.0% faster at 10 seeds and the cold sweep start training at 89.7 and 99.8 s; not
#            adopted (benchmarks/results/2026-11-27-h100-topn/).
#   learn-more five more seeds of the learning benchmark on $LEARN_TASK (default ant), seeds $LEARN_FIRST (default 5)
#            to LEARN_FIRST + 4, for cdjax's model-free arm (vmapped, one process) and Brax PPO (one seed at a time, in
#            two processes of 3 and 2 seeds, since its evaluations are latency-bound), side by side (about 9 minutes).
#            On 2026-11-27 (H100), seeds 5-9: with the committed rows of seeds 0-4, ant's final IQM was 2422.5 [2263.1,
#            2651.4] over 10 seeds against Brax PPO's 2378.5 over its 9 complete ones; one Brax process of 5 seeds ran
#            out of time in its last seed (benchmarks/results/2026-11-27-h100-learn-more/).
#   tuned    cdjax's `tuned` compile mode (per program: XLA's own autotuner level and GEMM tiling search) against its
#            defaults, about 11 minutes: the seeds suite's Mb-Mf and paper-CD at 10 vmapped seeds of 256 envs at the
#            defaults, in the mode, and with XLA's own tiling search alone (process-wide: which of the two settings
#            the 10-seed gain of the `outer` unit's xla-own part comes from); then the compare suite in the mode (Brax
#            PPO stays at cdjax's process flags), and the cold 4-arm ant sweep compiled in it. On 2026-11-27 (H100)
#            paper-CD at 10 seeds 0.528 s per update in the mode against 0.586 at the defaults, 0.525 with the tiling
#            search alone; the cold sweep 97.0 s (benchmarks/results/2026-11-27-h100-tuned/).
#   shares   the SGD's logged loss values as per-sample shares (cdjax's default since 2026-11-27) against scalars
#            reduced in every step (`benchmarks.variants scalar-loss-metrics`, the code before), each in a process of
#            its own (about 12 minutes): the seeds suite's Mb-Mf and paper-CD at 10 vmapped seeds of 256 envs, then the
#            compare suite's model-free, Mb-Mf and paper-CD. Under vmap two of those reductions made a 3-block kernel of
#            the losses' backward (18.7 ms of Mb-Mf's 0.419 s update at 10 seeds; hlo-seeds, 2026-11-27). On 2026-11-27
#            (H100): 10 seeds Mb-Mf 0.4038 against 0.4242 s/update, paper-CD 0.7015 against 0.7304; one seed 1-2%
#            (benchmarks/results/2026-11-27-h100-shares/).
#   outer    the `outer-dense` variant (benchmarks.variants: every dense layer of the agent's MLPs with its kernel's and
#            bias's gradients as one product of [inputs, 1] with the cotangents) and XLA's own autotuner level and GEMM
#            search (as `xla-own`), each against the agent at cdjax's defaults, in processes of their own (about 16
#            minutes): the compare suite (Brax PPO, model-free, Mb-Mf, paper-CD; Brax PPO's own layers are not changed
#            by the variant), then the seeds suite's Mb-Mf and paper-CD at 10 vmapped seeds of 256 envs. Whether the bias
#            and split-K reductions of the dense layers' backward (about 35 of model-free's 104 kernels per SGD step,
#            benchmarks/results/2026-11-27-h100-hlo-model-free/) cost what issue 21's model-free target lacks (0.373 s
#            per update against the 0.345 s that 1.5x Brax PPO's 0.518 s needs, 2026-11-27), and whether cdjax's
#            autotuner level and tilings cost the 10-seed paper-CD update 10% (`xla-own`).
#   chunks   the `grad-chunks` variant (benchmarks.variants: the consistency chain's weight gradients as one product
#            per 5 steps, each free to run as soon as its steps' cotangents exist, instead of one product over all 20
#            steps after the backward loop, with its stacks of every step's arrays) against the agent as it is: the
#            compare suite's Mb-Mf and paper-CD four times (ABBA), then the seeds suite's Mb-Mf and paper-CD at 10
#            vmapped seeds of 256 envs with and without (about 14 minutes).
#   kcache   XLA's kernel cache file (--xla_gpu_kernel_cache_file: the kernels of a compiled program are written to a
#            file, and a later compile reuses the kernels whose fused computation it already holds): the cold 4-arm ant
#            sweep at cdjax's defaults and with a fresh cache file, ABBA (about 6 minutes). The chunks all hold the
#            ant's physics (about 7,000 operations each, 35-60% of a chunk); whether the programs compiled before the
#            chunks, or the chunks one another, spare them compiling its kernels. On 2026-11-27 (H100): training after
#            80.7 and 75.4 s at the defaults, 73.0 and 75.2 s with the file: within the spread, not adopted
#            (benchmarks/results/2026-11-27-h100-kcache/).
#   concurrent  XLA's CUDA graphs scheduled by data flow (--xla_gpu_command_buffer_scheduling_mode=CONCURRENT: a
#            graph's kernels wait only on those whose buffers they use; cdjax's default for its own programs,
#            cdjax.runtime.compiler_options) against
#            XLA's own program order (LHS), as `cmdbuf` does its flag (about 10 minutes). On 2026-11-27 (H100, run
#            then as CONCURRENT against the default) every case 9.5-22% faster with CONCURRENT, Brax PPO's too
#            (benchmarks/results/2026-11-27-h100-concurrent/).
#   xla-own  cdjax's autotuner level and GEMM tilings (level 1, the cost model's top 2: cdjax.runtime.XLA_DEFAULTS)
#            against XLA's own (XLA_FLAGS=--xla_gpu_autotune_level=4 --xla_gpu_experimental_cost_model_gemm_tiling_options=),
#            as `concurrent` does its flag (flag_ab; about 10 minutes). Their cost at run time was measured only with the
#            benchmarks running at XLA's own flags by mistake (the harness bug found on 2026-11-27,
#            benchmarks/results/2026-11-27-h100-rerun/), and on 2026-11-27 (H100) the 10-seed paper-CD update took 0.582 s
#            at cdjax's defaults against 0.529 s at XLA's level and search in an earlier lease
#            (benchmarks/results/2026-11-27-h100-per-program/).
#   determinism  the `deterministic` compile mode (CDJAX_COMPILE_MODE) in two processes, model-free and paper-CD, both
#            programs (init and update) compiled in the mode; then XLA's deterministic ops alone, at cdjax's autotuner
#            level, two processes of paper-CD (--base xla_gpu_deterministic_ops=true), and what they cost per update: the
#            compare suite's model-free, Mb-Mf and paper-CD with XLA_FLAGS=--xla_gpu_deterministic_ops=true (about 9
#            minutes). On 2026-11-27 (H100) the mode cost 1.71-1.87x per update, and the deterministic ops alone made two
#            model-free processes identical (benchmarks/results/2026-11-27-h100-per-program/); re-run, the mode and
#            the ops alone each gave identical arrays, and the ops alone cost about 1.86x
#            (benchmarks/results/2026-11-27-h100-determinism/).
#   identity whether cdjax's graph scheduling (CONCURRENT) computes what XLA's own (LHS) does, bit for bit (about
#            12 minutes in all): `python -m benchmarks.same_results` on the compare suite's model-free, Mb-Mf and
#            paper-CD cases, 3 updates each from key 0 in a process per mode (LHS twice: what two processes differ
#            by anyway), every array of the state and every metric compared, with the GPU's atomics and the autotuner's choices out of
#            the way (--base xla_gpu_deterministic_ops=true xla_gpu_autotune_level=0: without them, on 2026-11-27,
#            two LHS processes already differed in half the arrays, benchmarks/results/2026-11-27-h100-identity/);
#            then two processes in cdjax's `deterministic` compile mode (CDJAX_COMPILE_MODE; model-free and paper-CD):
#            whether the mode makes a GPU run repeat bit for bit (about 3 minutes);
#            then the pixel presets' update of 30 runs (experiments.pixel.roofline, as in `levels`) as cdjax compiles
#            it (CONCURRENT, in program order where it would not fit: it asked for 49.5 GiB at once when CONCURRENT was
#            process-wide) and at LHS.
#   kernels  A/Bs for the chain's per-step kernels (about 4-6 minutes): the names of XLA GPU flags in this image's
#            jaxlib (xla-gpu-flags.txt: candidates; jax 0.11.2 refused --xla_gpu_enable_split_k_autotuning, 2026-11-25,
#            and --xla_gpu_experimental_enable_split_k_rewrite, listed there, 2026-11-26); the compare
#            suite's Mb-Mf and paper-CD cases with XLA's defaults, then with split-K's rewrite off
#            (--xla_gpu_experimental_enable_split_k_rewrite=false, where the image knows it; the 2026-11-25 H100 HLO of
#            paper-CD's SGD step held 475 kernels against Mb-Mf's 140, among them pads of split-K products'
#            contracting size) and with Triton for every GEMM (--xla_gpu_triton_gemm_any=true: epilogues fused
#            into more products), profiled. Each flag is skipped, saying so, where the image's XLA refuses it
#            (`python -m benchmarks.xla_flags --accepts`). On 2026-11-26 (H200): Mb-Mf 0.4320, paper-CD 0.7072 s/update
#            (1.64x) with the defaults; triton_gemm_any 0.4354 and 0.7147 (benchmarks/results/2026-11-26-h200-kernels/).
#   autotune XLA's GPU autotuner at lower levels (about 7 minutes a level): the 4-arm ant sweep cold (an empty
#            persistent cache) with XLA_FLAGS=--xla_gpu_autotune_level=L for L in LEVELS (default "1"; XLA's default is 4,
#            which also initialises buffers and checks each candidate's results against a reference; 0, no autotuning,
#            cost the CD arm 0.66x on 2026-11-24), then what each level costs at run time: the compare suite's
#            model-free, Mb-Mf and paper-CD cases in a process per level, and once at XLA's default level 4. A level the
#            image's XLA refuses is skipped, saying so. Whether the cold start can come near 60 s without the 1.05-1.19x
#            steady-state cost of Triton's GEMMs off (`--compile-mode fast`).
#   top1     the GEMM tilings' cost model keeping its single best Triton tiling (top=1) against cdjax's default
#            (top=2): the 4-arm ant sweep cold twice each (ABBA), then the compare suite's model-free, Mb-Mf and
#            paper-CD cases in a process each (about 13 minutes). Whether one candidate fewer per fusion buys compile
#            time without run time.
#   seeds    the seeds suite's part of `accept` alone (about 4 minutes): 10 vmapped seeds of 256 envs, Mb-Mf and the
#            paper's CD, each with an op-level profile of one update of all ten seeds (--trace): what the 10-seed ratio
#            is made of.
#   levels   cdjax's autotuner level (level 1 since `import cdjax` adds GPU_AUTOTUNE_FLAG, cdjax/runtime.py) against
#            XLA's own (XLA_FLAGS=--xla_gpu_autotune_level=4) in one lease: the 4-arm ant sweep cold
#            (an empty persistent cache each) with cdjax's defaults, with level 4, and in `--compile-mode fast`
#            (CDJAX_COMPILE_MODE=fast: Triton's GEMMs off per program, at level 1); then the pixel presets' update
#            (experiments.pixel.roofline, halfcheetah, 30 runs, synthetic batch) at cdjax's level and at level 4: the
#            convolutions are autotuned too, so what level 1 picks for them is timed against level 4's picks; then the
#            compare suite (Brax PPO, model-free, Mb-Mf, paper-CD; one process, all at cdjax's level) (about 14 minutes
#            in all).
#   tilings  cdjax's GEMM tilings option (GPU_GEMM_TILINGS_FLAG, cdjax/runtime.py: XLA's cost model keeps the 2 best
#            of its default Triton tilings for the autotuner; default since 60ffa09) against XLA's own search
#            (XLA_FLAGS=--xla_gpu_experimental_cost_model_gemm_tiling_options=, named empty) in one lease (about 16
#            minutes): the 4-arm ant sweep cold at each; the pixel presets' update (as in `levels`) at each; then the
#            compare suite (Brax PPO, model-free, Mb-Mf, paper-CD) in a process per setting. On 2026-11-27 (one H100,
#            16 cores; benchmarks/results/2026-11-27-h100-gemm-tilings/) the sweep compiled in 57.2 s against 79.7 s
#            and Mb-Mf and paper-CD ran the same time per update; model-free, Brax PPO and the pixel update were not
#            timed: whether the option costs any case at run time. A second lease the same day (another H100 host,
#            benchmarks/results/2026-11-27-h100-tilings-learning/): 79.6 against 92.5 s, the pixel update 164.0
#            against 162.6 ms, the compare suite at the default as on other hosts; its last part (the compare suite at
#            XLA's own search) was stopped to leave the lease to `learn`.
#   timers   where XLA:GPU's compile time goes (about 3 minutes): the cold 4-arm ant sweep at cdjax's defaults with
#            XLA's own timers logged (TF_CPP_VMODULE=gpu_compiler=1,nvptx_compiler=1,compile_module_to_llvm_ir=1; the
#            timer lines kept as timers.log.gz), summed per timer and kind of module by benchmarks.xla_timers (timers.md,
#            timers.json). On 2026-11-27 at XLA's own tilings (16 cores, benchmarks/results/2026-11-27-h100x4-compile-cores/)
#            the autotuner's Triton GEMM candidates took the largest share; this shows what is left at the defaults.
#   sched    whether the chunks, compiling side by side, each autotune the kernels they share (about 7 minutes): the
#            cold 4-arm ant sweep at cdjax's defaults and with `benchmarks.compile_time --first-chunk-alone` (the other
#            chunks start compiling once the first is compiled, so XLA's in-process autotuning results can serve
#            them), twice each, alternating. If the second is faster, sharing the autotuning is the lever for the
#            60 s target on 16 cores. The four chunks hold 237 distinct matrix product signatures summed, 94 across
#            them (CPU, benchmarks/results/2026-11-27-cpu-dot-signatures/).
#   learn    the learning benchmark alone (parallel's last part, about 10 minutes): cdjax's model-free arm at its defaults,
#            5 seeds, ant, halfcheetah and reacher side by side on the one GPU; the rows to set beside Brax PPO's.
#   parallel XLA's LLVM module compilation in parallel (about 11 minutes): the 4-arm ant sweep cold at cdjax's defaults,
#            then with XLA_FLAGS=--xla_gpu_enable_llvm_module_compilation_parallelism=true (XLA splits each program's
#            LLVM module and compiles the parts in threads; off by default), then with it and
#            --xla_gpu_force_compilation_parallelism=8 (the thread count named); each flag skipped, saying so, where the
#            image's XLA refuses it. Then the learning benchmark (cdjax's model-free arm, 5 seeds, ant, halfcheetah and
#            reacher side by side on the one GPU, as on 2026-11-25) at cdjax's defaults: the rows to set beside Brax
#            PPO's (`python -m benchmarks.learning --report`), owed since the autotuner's level 1 (5043691). On 2026-11-26
#            (H100) jax 0.11.2's XLA refused both flags, and half-cheetah hit the then 420 s limit at 2.9M of 3.9M env
#            steps (each task now has 600 s; ant and reacher finished).
#   workers  how many compiling threads the cold 4-arm ant sweep wants (about 5 minutes): the sweep cold (an empty
#            persistent cache each) with CDJAX_COMPILE_WORKERS=W for W in WORKERS (default "2 4 8"; 8 is the default on
#            these 16-core hosts). On 2026-11-26 (H100, level 1) the four chunks compiled side by side for 44-62 s each,
#            model-free's in 42-44 s where its one-update program compiles alone in 17 s: whether fewer threads (less
#            contention for the CPU and the one GPU's autotuner, and fusions autotuned once and then found in XLA's
#            in-process results) start training sooner. Cold times spread ~20% between H100 hosts, so compare within
#            the unit only. Result (2026-11-26, H100): 93.2, 71.1 and 73.2 s at 2, 4 and 8; the default stays
#            (benchmarks/results/2026-11-26-h100-workers/).
#   hc-seeds the learning benchmark's half-cheetah at 10 seeds a learner (about 8 minutes): cdjax's model-free arm,
#            seeds 0-9 in one process, then Brax PPO's seeds 5-9 (its seeds 0-4 are 2026-11-22's rows), one after
#            the other (side by side on one GPU they did not finish in one call, 2026-11-26). At level 1 the 5-seed
#            final IQM fell below Brax's (1740 against 1930, intervals overlapping; benchmarks/results/
#            2026-11-26-h100-learning/): whether that is the seeds' spread. On 2026-11-26 Brax's 5 seeds took
#            175-270 s each and the 480 s limit stopped it after seed 6; `hc-final` and a call of its own did the rest
#            (benchmarks/results/2026-11-26-h100-halfcheetah-seeds/).
#   hc-levels whether cdjax's autotuner level changes how half-cheetah learns (about 18 minutes): cdjax's model-free
#            arm, 20 seeds vmapped, once at XLA's level 4 (XLA_FLAGS=--xla_gpu_autotune_level=4: autotuning with
#            initialised buffers and each candidate's results checked against a reference) and once at cdjax's level
#            1 (no such check), each in a process of its own with its own cache; then Brax PPO's seed 9. On
#            2026-11-26 (H100) it found no difference: IQM 1533 against 1542 at 2.9M env steps, the same seed about
#            the same return at either level (benchmarks/results/2026-11-26-h100-halfcheetah-seeds/). Its limits
#            were 300 s then and cut every run after the 2.9M evaluation; they are 420 s now.
#   hc-final half-cheetah's 10-seed comparison finished (about 8 minutes): cdjax's model-free arm at seeds 10-19 (its
#            seeds 0-9 are `hc-seeds`' rows), then Brax PPO's seed 9 alone (`hc-levels` cut it at 2.9M env steps).
#   hc-ablate what decides which half-cheetah seeds fail (about 13 minutes): cdjax's model-free arm at 20 seeds vmapped,
#            at its defaults, with `--variants orthogonal-init` (its weights before 2026-11-22) and with `gae-once`
#            (GAE once per update with the rollout's values, as Brax PPO does), each in a process of its own. With
#            the default lecun-uniform weights 5 of 20 seeds ended under 700 (2026-11-26) against 1 of Brax's 10; with
#            orthogonal weights the 5 seeds of 2026-11-22 ended at 2630-3214, where lecun-init's ended at 1010-3618
#            (benchmarks/results/2026-11-22-h200-learning-lecun/). Lecun weights were adopted for ant (2128 -> 2833).
#   init     lecun-uniform weights with the policy head's 100x smaller (`--variants lecun-small-head`, orthogonal's
#            head) on the three learning tasks (about 25 minutes): half-cheetah at 20 seeds (hc-ablate, 2026-11-26:
#            lecun 1963.0 [1401.9, 2547.0], orthogonal 3073.7 [2823.7, 3198.7]), ant at 10 seeds with and without it
#            (orthogonal's 2128 against lecun's 2833 on 2026-11-22 is why lecun is the default), reacher at 10 seeds.
#            Each in a process of its own, stopped by `timeout`; the report of the four at the end.
#   head     the policy head's initial weights 10x smaller (`--variants head-0.1`: Config.policy_head_scale=0.1), between
#            lecun's (ant's best) and lecun-small-head's (half-cheetah's): half-cheetah at 20 seeds, ant and reacher at
#            10, then ant at 10 seeds with `orthogonal-init` (about 15 minutes). Report at the end. `init` and `head` ran
#            on 2026-11-26 (benchmarks/results/2026-11-26-h100-head/) at ca7d478, when `default` was Brax's head: x0.1
#            is the default since, so `init`'s `default` part now runs x0.1 (`brax-head` is the old one).
#   head-more the x0.1 default's ant figure at more seeds: Brax PPO's ant seeds 5-9 (its 2026-11-22 rows hold 0-4),
#            cdjax's ant at 10 more seeds (base key 1: seeds 1000-1009) at x0.1 (the default) and with Brax's head
#            (`brax-head`), and reacher at 10 seeds with Brax's head (beside `head`'s x0.1 rows; its 200 s limit, 280 s since, cut
#            it at 13.1M of 19.7M steps). Report at the end. Ran 2026-11-26 (1165 s on one H100):
#            benchmarks/results/2026-11-26-h100-head-more/.
#   (noclip, the consistency term without the normalisation's clip (its fused chain folding the model's output layer
#            into the next step's input product), ran on 2026-11-26 on one H200 and was removed with Config.cc_clip:
#            paper-CD 0.7971 and 0.7944 s/update unclipped against 0.7158 and 0.7122 s clipped; 10 vmapped seeds 1.87x
#            Mb-Mf; cold 4-arm compile 82.8 s; benchmarks/results/2026-11-26-h200-noclip/.)
#   (merged, an A/B of the fused chain's per-step products as block-diagonal ones, ran on 2026-11-26 and was removed
#            with that variant: paper-CD 0.7982 and 0.8031 s/update with it against 0.7338 and 0.7355 s without;
#            benchmarks/results/2026-11-26-h100-merged/.)
#   (stream, the fused chain's forward and backward as calls on a second GPU stream (`benchmarks.variants
#            chain-stream`), ran on 2026-11-26 and was removed with that variant: paper-CD 0.7687 s/update with it and
#            0.7675 s with its calls but without the stream flag, against 0.7335 s; benchmarks/results/2026-11-26-h100-stream/.)
#   (narrow, the chain's narrow per-step products at float32's highest precision and through weights padded to 128
#            columns, ran on 2026-11-26 and was removed with those variants: both slower, 0.7633 and 0.7399 against
#            0.7291 s/update; benchmarks/results/2026-11-26-h100-narrow/.)
# Since 5043691 `import cdjax` adds --xla_gpu_autotune_level=1 to XLA_FLAGS unless they name a level: "XLA's defaults"
# above means level 1 for the units run since, Triton's GEMM flag and the others set beside it; `autotune` and `levels`
# name level 4 (XLA's own default) where they compare against it. The units' earlier results ran at level 4.
# Each call waits up to WAIT_S seconds (default 560) for the unit, then says RUNNING (call again at once) or DONE,
# after packing into $OUT (default runs/compile-units-out) UNIT.tar.gz (every compile_time.json, lowered.json and
# log) and UNIT.log. The runs' checkpoints are not kept.
set -u
unit=$1; wait_s=${2:-560}
work=runs/compile-units/$unit
out=${OUT:-runs/compile-units-out}
t0=$(date +%s)
export PYTHONUNBUFFERED=1
sweep="--env ant --arms model-free mbmf cd-k5 cd --seeds 3"
cd_run="--env ant --arms cd --seeds 3 --steps 8000000 --no-final-eval --no-progress"

with_flag() {  # FLAGS ("NAME=VALUE", or several separated by spaces) COMMANDS -> a bash line: COMMANDS with
  # XLA_FLAGS=--FLAG ... where this image's XLA takes every one (it aborts on one it does not know), else a sentence
  # saying they were skipped
  local flag=$1; shift
  local exported
  exported=$(printf -- '--%s ' $flag)
  echo "if python -m benchmarks.xla_flags --accepts $flag > /dev/null; then (export XLA_FLAGS='${exported% }'; $*);" \
    "else echo 'this XLA refuses ${flag%%=*}: skipped'; fi;"
}

flag_ab() {  # FLAG NAME -> a bash line: the compare suite (Brax PPO, model-free, Mb-Mf, paper-CD; ant, 4096 envs) and
  # the seeds suite's Mb-Mf and paper-CD at 10 vmapped seeds of 256 envs, each in a process at cdjax's defaults
  # ($work/compare-default, seeds-default) and in one with XLA_FLAGS=--FLAG (compare-NAME, seeds-NAME), about 10 minutes
  local flag=$1 name=$2
  local cases="--suite compare --cases brax-ppo model-free mbmf cd-paper --budget-s 250"
  local seeds="--suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 --budget-s 150"
  echo "timeout -k 20 280 python -m benchmarks.run $cases --out $work/compare-default > $work/compare-default.log 2>&1;" \
    "grep -H 's/update' $work/compare-default.log;" \
    "$(with_flag "$flag" "timeout -k 20 280 python -m benchmarks.run $cases --out $work/compare-$name" \
      "> $work/compare-$name.log 2>&1")" \
    "grep -H 's/update' $work/compare-$name.log;" \
    "timeout -k 20 200 python -m benchmarks.run $seeds --out $work/seeds-default > $work/seeds-default.log 2>&1;" \
    "$(with_flag "$flag" "timeout -k 20 200 python -m benchmarks.run $seeds --out $work/seeds-$name" \
      "> $work/seeds-$name.log 2>&1")" \
    "grep -H -E 's/update|rror' $work/seeds-*.log $work/compare-*.log | grep -v -i warn"
}

dumped_case() {  # CASE MODULE PART "MODULE_AND_ARGS" GREP -> a bash line: `python -m MODULE_AND_ARGS` with XLA's
  # optimised HLO of the modules MODULE dumped into $work/dump-CASE and one update traced into $work/trace-CASE
  # (results $work/PART-CASE), then benchmarks.hlo_fusions on them (fusions-CASE.log, loops-CASE.log) and the lines
  # of the run's log that match GREP
  local case=$1 module=$2 part=$3 run=$4 grep=$5
  echo "XLA_FLAGS='--xla_dump_to=$work/dump-$case --xla_dump_hlo_as_text --xla_dump_hlo_module_re=$module'" \
    "timeout -k 20 150 python -m $run --budget-s 130 --trace $work/trace-$case --out $work/$part-$case" \
    "> $work/$part-$case.log 2>&1;" \
    "python -m benchmarks.hlo_fusions $work/dump-$case --profile $work/trace-$case --top ${HLO_TOP:-8}" \
    "> $work/fusions-$case.log 2>&1; head -n 9 $work/fusions-$case.log;" \
    "python -m benchmarks.hlo_fusions $work/dump-$case --loops --top 12 > $work/loops-$case.log 2>&1;" \
    "head -n 3 $work/loops-$case.log; grep -h $grep $work/$part-$case.log;"
}

command_of() {  # UNIT -> the unit's commands (one bash line)
  case "$1" in
    flags)
      echo "python -m benchmarks.compile_time --out $work/default --cache-dir $work/cache-default -- $sweep" \
        "> $work/default.log 2>&1;" \
        "XLA_FLAGS=--xla_gpu_enable_triton_gemm=false python -m benchmarks.compile_time --out $work/no-triton-gemm" \
        "--cache-dir $work/cache-no-triton -- $sweep > $work/no-triton-gemm.log 2>&1;" \
        "CDJAX_COMPILE_WORKERS=1 python -m benchmarks.compile_time --out $work/serial --cache-dir $work/cache-serial" \
        "-- $sweep > $work/serial.log 2>&1;" \
        "python -m cdjax.cli sweep $cd_run --out $work/run-default --cache-dir $work/cache-run-default" \
        "> $work/run-default.log 2>&1;" \
        "XLA_FLAGS=--xla_gpu_enable_triton_gemm=false python -m cdjax.cli sweep $cd_run --out $work/run-no-triton" \
        "--cache-dir $work/cache-run-no-triton > $work/run-no-triton.log 2>&1;" \
        "grep -h -E 'sweep [12]:|compile [0-9.]+ s|Trained in' --exclude=unit.log $work/*.log" ;;
    lowered)
      echo "python -m benchmarks.compile_time --lower-only --out $work/lowered -- $sweep > $work/lowered.log 2>&1;" \
        "tail -n 8 $work/lowered.log" ;;
    speed)
      cases="--suite compare --cases brax-ppo model-free mbmf cd-paper --budget-s 360"
      echo "CDJAX_COMPILE_MODE=fast python -m benchmarks.compile_time --out $work/fast --cache-dir $work/cache-fast" \
        "-- $sweep > $work/fast.log 2>&1;" \
        "python -m benchmarks.run $cases --out $work/default > $work/default.log 2>&1;" \
        "XLA_FLAGS=--xla_gpu_enable_triton_gemm=false python -m benchmarks.run $cases --out $work/no-triton-gemm" \
        "> $work/no-triton-gemm.log 2>&1;" \
        "grep -h -E 'sweep [12]:|compile [0-9.]+ s' $work/fast.log;" \
        "tail -n 12 $work/default/results.md $work/no-triton-gemm/results.md" ;;
    accept)
      local budget=${ACCEPT_BUDGET:-330}
      echo "timeout -k 20 $((budget + 30)) python -m benchmarks.run --suite compare --cases" \
        "${ACCEPT_CASES:-brax-ppo model-free mbmf cd-paper}" \
        "--budget-s $budget --trace $work/trace --out $work/compare > $work/compare.log 2>&1;" \
        "timeout -k 20 240 python -m benchmarks.run --suite seeds --scaling-cases mbmf cd-paper --seed-counts 10" \
        "--seed-envs 256 --budget-s 210 --trace $work/trace-seeds --out $work/seeds > $work/seeds.log 2>&1;" \
        "timeout -k 20 240 python -m benchmarks.compile_time --out $work/cold --cache-dir $work/cache-cold -- $sweep" \
        "> $work/cold.log 2>&1;" \
        "grep -h -E 'sweep [12]:|compile [0-9.]+ s' $work/cold.log;" \
        "tail -n 14 $work/compare/results.md $work/seeds/results.md" ;;
    autotune)
      local cases="--suite compare --cases model-free mbmf cd-paper --budget-s 150" line="" level
      for level in ${LEVELS:-1}; do
        line+=" $(with_flag xla_gpu_autotune_level=$level "timeout -k 20 240 python -m benchmarks.compile_time" \
          "--out $work/level$level --cache-dir $work/cache-level$level -- $sweep > $work/level$level.log 2>&1;" \
          "timeout -k 20 180 python -m benchmarks.run $cases --out $work/run-level$level" \
          "> $work/run-level$level.log 2>&1")"
      done
      echo "$line XLA_FLAGS=--xla_gpu_autotune_level=4 timeout -k 20 180 python -m benchmarks.run $cases" \
        "--out $work/run-default > $work/run-default.log 2>&1;" \
        "grep -H -E 'sweep [12]:|compile [0-9.]+ s' $work/level*.log; grep -H ' s/update' $work/run-*.log" ;;
    levels)
      local rf="python -m experiments.pixel.roofline --env halfcheetah --runs 30 --variants bfloat16/per-run --synthetic"
      echo "python -c 'import os, cdjax; print(os.environ)' | grep -o -E 'XLA_FLAGS[^,]*' > $work/xla-flags.log 2>&1;" \
        "timeout -k 20 200 python -m benchmarks.compile_time --out $work/level1 --cache-dir $work/cache-level1" \
        "-- $sweep > $work/level1.log 2>&1;" \
        "XLA_FLAGS=--xla_gpu_autotune_level=4 timeout -k 20 240 python -m benchmarks.compile_time --out $work/level4" \
        "--cache-dir $work/cache-level4 -- $sweep > $work/level4.log 2>&1;" \
        "CDJAX_COMPILE_MODE=fast timeout -k 20 200 python -m benchmarks.compile_time --out $work/fast-level1" \
        "--cache-dir $work/cache-fast -- $sweep > $work/fast-level1.log 2>&1;" \
        "timeout -k 20 150 $rf --out $work/pixel-level1.json > $work/pixel-level1.log 2>&1;" \
        "XLA_FLAGS=--xla_gpu_autotune_level=4 timeout -k 20 150 $rf --out $work/pixel-level4.json" \
        "> $work/pixel-level4.log 2>&1;" \
        "timeout -k 20 330 python -m benchmarks.run --suite compare --cases brax-ppo model-free mbmf cd-paper" \
        "--budget-s 300 --out $work/compare > $work/compare.log 2>&1;" \
        "grep -H -E 'sweep [12]:|compile [0-9.]+ s' $work/level*.log $work/fast-level1.log;" \
        "cat $work/pixel-level1.md $work/pixel-level4.md; tail -n 14 $work/compare/results.md" ;;
    tilings)
      local rf="python -m experiments.pixel.roofline --env halfcheetah --runs 30 --variants bfloat16/per-run --synthetic"
      local cases="--suite compare --cases brax-ppo model-free mbmf cd-paper --budget-s 300" off
      off="XLA_FLAGS=--xla_gpu_experimental_cost_model_gemm_tiling_options="
      echo "python -c 'import os, cdjax; print(os.environ)' | grep -o -E 'XLA_FLAGS[^,]*' > $work/xla-flags.log 2>&1;" \
        "timeout -k 20 200 python -m benchmarks.compile_time --out $work/top2 --cache-dir $work/cache-top2" \
        "-- $sweep > $work/top2.log 2>&1;" \
        "$off timeout -k 20 200 python -m benchmarks.compile_time --out $work/xla --cache-dir $work/cache-xla" \
        "-- $sweep > $work/xla.log 2>&1;" \
        "timeout -k 20 150 $rf --out $work/pixel-top2.json > $work/pixel-top2.log 2>&1;" \
        "$off timeout -k 20 150 $rf --out $work/pixel-xla.json > $work/pixel-xla.log 2>&1;" \
        "timeout -k 20 330 python -m benchmarks.run $cases --out $work/compare-top2 > $work/compare-top2.log 2>&1;" \
        "$off timeout -k 20 330 python -m benchmarks.run $cases --out $work/compare-xla > $work/compare-xla.log 2>&1;" \
        "grep -H -E 'sweep [12]:|compile [0-9.]+ s' $work/top2.log $work/xla.log;" \
        "cat $work/pixel-top2.md $work/pixel-xla.md; grep -H ' s/update' $work/compare-*.log" ;;
    kernels)
      local cases="--suite compare --cases mbmf cd-paper --budget-s 120" flag line
      line="python -m benchmarks.xla_flags > $work/xla-gpu-flags.txt; wc -l < $work/xla-gpu-flags.txt;"
      line+=" timeout -k 20 150 python -m benchmarks.run $cases --out $work/default > $work/default.log 2>&1;"
      for flag in xla_gpu_experimental_enable_split_k_rewrite=false xla_gpu_triton_gemm_any=true; do
        line+=" $(with_flag $flag "timeout -k 20 170 python -m benchmarks.run $cases --trace $work/trace-${flag%%=*}" \
          "--out $work/${flag%%=*} > $work/${flag%%=*}.log 2>&1")"
      done
      echo "$line grep -H ' s/update' $work/default.log $work/xla_gpu_*.log" ;;
    hlo)
      local line="" case run base
      for case in ${HLO_CASES:-mbmf mbmf-nometrics cd-paper cd-paper-biassum}; do
        case $case in
          *-nometrics) run="benchmarks.variants no-loss-metrics --" ;;
          *-biassum) run="benchmarks.variants bias-sum --" ;;
          *) run="benchmarks.run" ;;
        esac
        base=${case%-nometrics}; base=${base%-biassum}
        line+=" $(dumped_case $case jit_update compare "$run --suite compare --cases $base" "' s/update'")"
      done
      echo "$line find $work -name '*after_optimizations.txt' | xargs tar -czf $work/hlo.tar.gz" ;;
    hlo-seeds)
      local line="" case
      for case in mbmf cd-paper; do
        line+=" $(dumped_case $case jit_run seeds \
          "benchmarks.run --suite seeds --scaling-cases $case --seed-counts 10 --seed-envs 256" "'x10:'")"
      done
      echo "$line find $work -name '*after_optimizations.txt' | xargs tar -czf $work/hlo.tar.gz" ;;
    workers)
      local line="" w
      for w in ${WORKERS:-2 4 8}; do
        line+="CDJAX_COMPILE_WORKERS=$w timeout -k 20 200 python -m benchmarks.compile_time --out $work/workers$w"
        line+=" --cache-dir $work/cache-workers$w -- $sweep > $work/workers$w.log 2>&1; "
      done
      echo "$line grep -H -E 'sweep [12]:|compile [0-9.]+ s' $work/workers*.log" ;;
    hc-seeds)
      echo "timeout -k 20 240 python -m benchmarks.learning --tasks halfcheetah --frameworks cdjax --variants default" \
        "--seeds 10 --out $work/learn/halfcheetah > $work/learn-halfcheetah.log 2>&1;" \
        "timeout -k 20 480 python -m benchmarks.learning --cache-dir $work/cache-brax --tasks halfcheetah" \
        "--frameworks brax --seeds 5 --first-seed 5 --out $work/learn/brax-halfcheetah-5-9" \
        "> $work/learn-brax.log 2>&1;" \
        "tail -n 3 $work/learn-halfcheetah.log $work/learn-brax.log" ;;
    hc-levels)
      local learn="python -m benchmarks.learning --tasks halfcheetah --frameworks cdjax --variants default --seeds 20"
      echo "XLA_FLAGS=--xla_gpu_autotune_level=4 timeout -k 20 420 $learn --cache-dir $work/cache-l4" \
        "--out $work/learn/level4 > $work/learn-level4.log 2>&1;" \
        "timeout -k 20 420 $learn --cache-dir $work/cache-l1 --out $work/learn/level1 > $work/learn-level1.log 2>&1;" \
        "timeout -k 20 330 python -m benchmarks.learning --cache-dir $work/cache-brax --tasks halfcheetah" \
        "--frameworks brax --seeds 1 --first-seed 9 --out $work/learn/brax-halfcheetah-9 > $work/learn-brax.log 2>&1;" \
        "tail -n 2 $work/learn-*.log" ;;
    hc-final)
      echo "timeout -k 20 280 python -m benchmarks.learning --tasks halfcheetah --frameworks cdjax --variants default" \
        "--seeds 10 --first-seed 10 --out $work/learn/halfcheetah-10-19 > $work/learn-halfcheetah.log 2>&1;" \
        "timeout -k 20 330 python -m benchmarks.learning --cache-dir $work/cache-brax --tasks halfcheetah" \
        "--frameworks brax --seeds 1 --first-seed 9 --out $work/learn/brax-halfcheetah-9 > $work/learn-brax.log 2>&1;" \
        "tail -n 2 $work/learn-*.log" ;;
    hc-ablate)
      local learn="python -m benchmarks.learning --tasks halfcheetah --frameworks cdjax --seeds 20" line="" v
      for v in default orthogonal-init gae-once; do
        line+="timeout -k 20 420 $learn --variants $v --out $work/learn/$v > $work/learn-$v.log 2>&1; "
      done
      echo "$line python -m benchmarks.learning --report $work/learn/default $work/learn/orthogonal-init" \
        "$work/learn/gae-once --write $work/report.md > /dev/null 2>&1; tail -n 14 $work/report.md" ;;
    init)
      local learn="python -m benchmarks.learning --frameworks cdjax"
      echo "timeout -k 20 300 $learn --tasks halfcheetah --seeds 20 --variants lecun-small-head" \
        "--out $work/learn/halfcheetah-small > $work/learn-halfcheetah-small.log 2>&1;" \
        "timeout -k 20 420 $learn --tasks ant --seeds 10 --variants lecun-small-head" \
        "--out $work/learn/ant-small > $work/learn-ant-small.log 2>&1;" \
        "timeout -k 20 420 $learn --tasks ant --seeds 10 --variants default --out $work/learn/ant-default" \
        "> $work/learn-ant-default.log 2>&1;" \
        "timeout -k 20 360 $learn --tasks reacher --seeds 10 --variants lecun-small-head" \
        "--out $work/learn/reacher-small > $work/learn-reacher-small.log 2>&1;" \
        "python -m benchmarks.learning --report $work/learn/* --write $work/report.md > /dev/null 2>&1;" \
        "tail -n 3 $work/learn-*.log; grep -A12 '^### Ablation' $work/report.md" ;;
    head)
      local learn="python -m benchmarks.learning --frameworks cdjax"
      echo "timeout -k 20 420 $learn --tasks halfcheetah --seeds 20 --variants head-0.1" \
        "--out $work/learn/halfcheetah-head > $work/learn-halfcheetah-head.log 2>&1;" \
        "timeout -k 20 240 $learn --tasks ant --seeds 10 --variants head-0.1 --out $work/learn/ant-head" \
        "> $work/learn-ant-head.log 2>&1;" \
        "timeout -k 20 240 $learn --tasks reacher --seeds 10 --variants head-0.1 --out $work/learn/reacher-head" \
        "> $work/learn-reacher-head.log 2>&1;" \
        "timeout -k 20 200 $learn --tasks ant --seeds 10 --variants orthogonal-init --out $work/learn/ant-orthogonal" \
        "> $work/learn-ant-orthogonal.log 2>&1;" \
        "tail -n 2 $work/learn-*.log" ;;
    head-more)
      local learn="python -m benchmarks.learning --frameworks cdjax"
      echo "timeout -k 20 240 $learn --tasks ant --seeds 10 --first-seed 1 --variants default" \
        "--out $work/learn/ant-default-1 > $work/learn-ant-default-1.log 2>&1;" \
        "timeout -k 20 240 $learn --tasks ant --seeds 10 --first-seed 1 --variants brax-head" \
        "--out $work/learn/ant-brax-head-1 > $work/learn-ant-brax-head-1.log 2>&1;" \
        "timeout -k 20 280 $learn --tasks reacher --seeds 10 --variants brax-head --out $work/learn/reacher-brax-head" \
        "> $work/learn-reacher-brax-head.log 2>&1;" \
        "timeout -k 20 540 python -m benchmarks.learning --cache-dir $work/cache-brax --tasks ant --frameworks brax" \
        "--seeds 5 --first-seed 5 --out $work/learn/brax-ant-5-9 > $work/learn-brax-ant.log 2>&1;" \
        "python -m benchmarks.learning --report $work/learn/* --write $work/report.md > /dev/null 2>&1;" \
        "tail -n 2 $work/learn-*.log" ;;
    parallel)
      local llvm=xla_gpu_enable_llvm_module_compilation_parallelism=true t
      echo "timeout -k 20 200 python -m benchmarks.compile_time --out $work/default --cache-dir $work/cache-default" \
        "-- $sweep > $work/default.log 2>&1;" \
        "$(with_flag $llvm "timeout -k 20 200 python -m benchmarks.compile_time --out $work/llvm" \
          "--cache-dir $work/cache-llvm -- $sweep > $work/llvm.log 2>&1")" \
        "if python -m benchmarks.xla_flags --accepts $llvm xla_gpu_force_compilation_parallelism=8 > /dev/null; then" \
        "XLA_FLAGS='--$llvm --xla_gpu_force_compilation_parallelism=8' timeout -k 20 200 python -m benchmarks.compile_time" \
        "--out $work/llvm8 --cache-dir $work/cache-llvm8 -- $sweep > $work/llvm8.log 2>&1;" \
        "else echo 'this XLA refuses force_compilation_parallelism: skipped'; fi;" \
        "grep -H -E 'sweep [12]:|compile [0-9.]+ s' $work/default.log $work/llvm*.log;"
      for t in ant halfcheetah reacher; do
        echo "XLA_PYTHON_CLIENT_PREALLOCATE=false timeout -k 20 600 python -m benchmarks.learning --tasks $t" \
          "--frameworks cdjax --variants default --seeds 5 --out $work/learn/$t > $work/learn-$t.log 2>&1 &"
      done
      echo "wait; tail -n 2 $work/learn-*.log" ;;
    learn-more)
      # five more seeds of the learning benchmark on ${LEARN_TASK:-ant} from seed ${LEARN_FIRST:-5}: cdjax's model-free
      # arm (its seeds vmapped) beside Brax PPO (one seed at a time, in two processes), all on the one GPU
      local t=${LEARN_TASK:-ant} f=${LEARN_FIRST:-5} env="XLA_PYTHON_CLIENT_PREALLOCATE=false timeout -k 20 560"
      echo "$env python -m benchmarks.learning --tasks $t --frameworks cdjax --variants default --seeds 5" \
        "--first-seed $f --out $work/learn/$t-cdjax > $work/learn-$t-cdjax.log 2>&1 &" \
        "$env python -m benchmarks.learning --tasks $t --frameworks brax --seeds 3 --first-seed $f --budget-s 520" \
        "--cache-dir $work/jc --out $work/learn/$t-brax-a > $work/learn-$t-brax-a.log 2>&1 &" \
        "$env python -m benchmarks.learning --tasks $t --frameworks brax --seeds 2 --first-seed $((f + 3)) --budget-s 520" \
        "--cache-dir $work/jc2 --out $work/learn/$t-brax-b > $work/learn-$t-brax-b.log 2>&1 &" \
        "wait; tail -n 3 $work/learn-*.log" ;;
    sched)
      local line="" i v
      for i in 1 2; do
        for v in default first-alone; do
          local opt=""; [ $v = first-alone ] && opt="--first-chunk-alone"
          line+="timeout -k 20 200 python -m benchmarks.compile_time $opt --out $work/$v$i --cache-dir $work/cache-$v$i"
          line+=" -- $sweep > $work/$v$i.log 2>&1; "
        done
      done
      echo "$line grep -H -E 'sweep 1:|compile [0-9.]+ s' $work/*.log" ;;
    top1)
      local cases="--suite compare --cases model-free mbmf cd-paper --budget-s 170" one line=""
      one="XLA_FLAGS=--xla_gpu_experimental_cost_model_gemm_tiling_options=top=1,top_from_default=1"
      for v in top2a top1a top1b top2b; do
        local env=""; [ "${v:0:4}" = top1 ] && env="$one"
        line+="$env timeout -k 20 200 python -m benchmarks.compile_time --out $work/$v --cache-dir $work/cache-$v"
        line+=" -- $sweep > $work/$v.log 2>&1; "
      done
      line+="timeout -k 20 200 python -m benchmarks.run $cases --out $work/compare-top2 > $work/compare-top2.log 2>&1; "
      line+="$one timeout -k 20 200 python -m benchmarks.run $cases --out $work/compare-top1"
      line+=" > $work/compare-top1.log 2>&1; "
      echo "$line grep -H -E 'sweep 1:|compile [0-9.]+ s' $work/top*.log; grep -H ' s/update' $work/compare-*.log" ;;
    seeds)
      echo "timeout -k 20 280 python -m benchmarks.run --suite seeds --scaling-cases mbmf cd-paper --seed-counts 10" \
        "--seed-envs 256 --budget-s 250 --trace $work/trace --out $work/seeds > $work/seeds.log 2>&1;" \
        "grep -E 'env steps/s|s/update' $work/seeds.log; grep -A 30 'Op-level' $work/seeds/results.md | head -80" ;;
    cublaslt) flag_ab xla_gpu_enable_cublaslt=false legacy ;;
    regions)
      # per program (CDJAX_XLA_OPTIONS: cdjax's programs only, Brax PPO's at XLA's own), each suite in a process
      # without and one with it
      local cases="--suite compare --cases brax-ppo model-free mbmf cd-paper --budget-s 250" one=""
      local seeds="--suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 --budget-s 150"
      one="CDJAX_XLA_OPTIONS=xla_gpu_copy_insertion_use_region_analysis=true"
      echo "timeout -k 20 280 python -m benchmarks.run $cases --out $work/compare-default > $work/compare-default.log 2>&1;" \
        "$one timeout -k 20 280 python -m benchmarks.run $cases --out $work/compare-regions > $work/compare-regions.log 2>&1;" \
        "timeout -k 20 200 python -m benchmarks.run $seeds --out $work/seeds-default > $work/seeds-default.log 2>&1;" \
        "$one timeout -k 20 200 python -m benchmarks.run $seeds --out $work/seeds-regions > $work/seeds-regions.log 2>&1;" \
        "grep -H -E 's/update|rror' $work/compare-*.log $work/seeds-*.log | grep -v -i warn" ;;
    regions-hlo)
      local line="" case f=xla_gpu_copy_insertion_use_region_analysis=true
      for case in ${HLO_CASES:-model-free}; do
        line+=" $(dumped_case $case jit_update compare "benchmarks.run --suite compare --cases $case" "' s/update'")"
        line+=" CDJAX_XLA_OPTIONS=$f $(dumped_case $case-regions jit_update compare \
          "benchmarks.run --suite compare --cases $case" "' s/update'")"
      done
      echo "$line grep -H -E ' copy|kernels per' $work/loops-*.log | head -n 40;" \
        "find $work -name '*after_optimizations.txt' | xargs tar -czf $work/hlo.tar.gz" ;;
    cmdbuf) flag_ab xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL while ;;
    pdl) flag_ab xla_gpu_enable_pdl=true pdl ;;
    concurrent) flag_ab xla_gpu_command_buffer_scheduling_mode=LHS lhs ;;
    xla-own) flag_ab "xla_gpu_autotune_level=4 xla_gpu_experimental_cost_model_gemm_tiling_options=" xla-own ;;
    determinism)
      local lhs=xla_gpu_command_buffer_scheduling_mode=LHS
      echo "CDJAX_COMPILE_MODE=deterministic timeout -k 20 300 python -m benchmarks.same_results --flags $lhs $lhs" \
        "--cases model-free cd-paper --updates 3 --out $work/same-det > $work/same-det.log 2>&1;" \
        "grep -v -i warn $work/same-det.log | tail -n 6;" \
        "timeout -k 20 300 python -m benchmarks.same_results --flags $lhs $lhs --cases cd-paper" \
        "--base xla_gpu_deterministic_ops=true --updates 3 --out $work/same-ops > $work/same-ops.log 2>&1;" \
        "grep -v -i warn $work/same-ops.log | tail -n 5;" \
        "$(with_flag xla_gpu_deterministic_ops=true "timeout -k 20 240 python -m benchmarks.run --suite compare" \
          "--cases model-free mbmf cd-paper --budget-s 210 --out $work/compare-ops > $work/compare-ops.log 2>&1")" \
        "grep -H ' s/update\|rror' $work/compare-ops.log | grep -v -i warn" ;;
    determinism-cd)
      # the determinism unit's last part, which its lease cut: the compare suite's Mb-Mf and paper-CD under XLA's
      # deterministic ops alone (cdjax's other options as they are), in one process (about 4 minutes)
      echo "$(with_flag xla_gpu_deterministic_ops=true "timeout -k 20 280 python -m benchmarks.run --suite compare" \
          "--cases mbmf cd-paper --budget-s 250 --out $work/compare-ops > $work/compare-ops.log 2>&1")" \
        "grep -H ' s/update\\|rror' $work/compare-ops.log | grep -v -i warn" ;;
    identity)
      local lhs=xla_gpu_command_buffer_scheduling_mode=LHS
      local modes="$lhs $lhs xla_gpu_command_buffer_scheduling_mode=CONCURRENT"
      local rf="python -m experiments.pixel.roofline --env halfcheetah --runs 30 --variants bfloat16/per-run --synthetic"
      local base="xla_gpu_deterministic_ops=true xla_gpu_autotune_level=0"
      echo "base='$base'; python -m benchmarks.xla_flags --accepts \$base || base='xla_gpu_autotune_level=0';" \
        "echo \"base settings: \$base\";" \
        "timeout -k 20 420 python -m benchmarks.same_results --flags $modes --cases model-free mbmf cd-paper" \
        "--base \$base --updates 3 --out $work/same > $work/same.log 2>&1; grep -v -i warn $work/same.log | tail -n 12;" \
        "CDJAX_COMPILE_MODE=deterministic timeout -k 20 240 python -m benchmarks.same_results --flags $lhs $lhs" \
        "--cases model-free cd-paper --updates 3 --out $work/same-det > $work/same-det.log 2>&1;" \
        "grep -v -i warn $work/same-det.log | tail -n 6;" \
        "timeout -k 20 150 $rf --out $work/pixel-concurrent.json > $work/pixel-concurrent.log 2>&1;" \
        "XLA_FLAGS=--xla_gpu_command_buffer_scheduling_mode=LHS timeout -k 20 150 $rf --out $work/pixel-lhs.json" \
        "> $work/pixel-lhs.log 2>&1; cat $work/pixel-concurrent.md $work/pixel-lhs.md;" \
        "grep -H -o '\"in_order\": [a-z]*' $work/pixel-*.json" ;;
    ab)
      local run=${AB_RUN:-"benchmarks.run --suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 \
--budget-s 120"} line="" v dir i=0
      [ -f runs/ab-base/REVISION ] || { echo "runs/ab-base/ is missing: run bash benchmarks/ab_base.sh REV here" \
        "and carry runs/ab-base" >&2; return 1; }
      for v in head base base head; do
        i=$((i + 1)); dir=.; [ $v = base ] && dir=runs/ab-base
        line+="(cd $dir && timeout -k 20 ${AB_LIMIT:-200} python -m $run --out $PWD/$work/$v$i) > $work/$v$i.log 2>&1; "
      done
      local which="python -c 'import cdjax, os; print(os.path.dirname(cdjax.__file__))'"
      echo "echo head imports \$($which), base \$(cd runs/ab-base && $which), revision \$(cat runs/ab-base/REVISION);" \
        "$line grep -H -E 's/update' $work/head*.log $work/base*.log" ;;
    chain)
      echo "timeout -k 20 200 python -m benchmarks.chain_kernel --compare-modes --out $work/modes" \
        "> $work/modes.log 2>&1; grep -v -i warn $work/modes.log | tail -n 6;" \
        "timeout -k 20 400 python -m benchmarks.chain_kernel --cluster --out $work/chain > $work/chain.log 2>&1;" \
        "grep -v -i warn $work/chain.log | tail -n 30" ;;
    chain-e2e)
      local seeds="--suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 --budget-s 120"
      local cases="--suite compare --cases mbmf cd-paper --budget-s 150" mode=${CHAIN_MODE:-cluster}
      echo "timeout -k 20 170 python -m benchmarks.run $seeds --out $work/seeds-xla > $work/seeds-xla.log 2>&1;" \
        "CDJAX_CHAIN_KERNEL=$mode timeout -k 20 170 python -m benchmarks.run $seeds --out $work/seeds-kernels" \
        "> $work/seeds-kernels.log 2>&1;" \
        "timeout -k 20 200 python -m benchmarks.run $cases --out $work/compare-xla > $work/compare-xla.log 2>&1;" \
        "CDJAX_CHAIN_KERNEL=$mode timeout -k 20 200 python -m benchmarks.run $cases --out $work/compare-kernels" \
        "> $work/compare-kernels.log 2>&1;" \
        "grep -H -E 's/update|Error|error' $work/seeds-*.log $work/compare-*.log | grep -v -i warn" ;;
    shares)
      local seeds="--suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 --budget-s 150"
      local cases="--suite compare --cases model-free mbmf cd-paper --budget-s 170" v="benchmarks.variants"
      echo "timeout -k 20 200 python -m benchmarks.run $seeds --out $work/seeds-shares > $work/seeds-shares.log 2>&1;" \
        "timeout -k 20 200 python -m $v scalar-loss-metrics -- $seeds --out $work/seeds-scalars" \
        "> $work/seeds-scalars.log 2>&1;" \
        "timeout -k 20 200 python -m benchmarks.run $cases --out $work/compare-shares" \
        "> $work/compare-shares.log 2>&1;" \
        "timeout -k 20 200 python -m $v scalar-loss-metrics -- $cases --out $work/compare-scalars" \
        "> $work/compare-scalars.log 2>&1;" \
        "grep -H -E 'x10:|s/update' $work/seeds-*.log $work/compare-*.log" ;;
    outer)
      local seeds="--suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 --budget-s 110"
      local cases="--suite compare --cases brax-ppo model-free mbmf cd-paper --budget-s 180" v="benchmarks.variants"
      local own="xla_gpu_autotune_level=4 xla_gpu_experimental_cost_model_gemm_tiling_options="
      echo "timeout -k 20 210 python -m benchmarks.run $cases --out $work/compare-plain > $work/compare-plain.log 2>&1;" \
        "timeout -k 20 210 python -m $v outer-dense -- $cases --out $work/compare-outer" \
        "> $work/compare-outer.log 2>&1;" \
        "$(with_flag "$own" "timeout -k 20 210 python -m benchmarks.run $cases --out $work/compare-xla-own" \
          "> $work/compare-xla-own.log 2>&1")" \
        "timeout -k 20 140 python -m benchmarks.run $seeds --out $work/seeds-plain > $work/seeds-plain.log 2>&1;" \
        "timeout -k 20 140 python -m $v outer-dense -- $seeds --out $work/seeds-outer > $work/seeds-outer.log 2>&1;" \
        "$(with_flag "$own" "timeout -k 20 140 python -m benchmarks.run $seeds --out $work/seeds-xla-own" \
          "> $work/seeds-xla-own.log 2>&1")" \
        "grep -H -E 'x10:|s/update' $work/compare-*.log $work/seeds-*.log" ;;
    topn)
      # the cost model's top N GEMM tilings (cdjax's default keeps 2): whether a few more catch the 10-seed gain of
      # XLA's own search (the `tuned` unit) at less compile time
      local seeds="--suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 --budget-s 110" line="" n
      line="timeout -k 20 140 python -m benchmarks.run $seeds --out $work/seeds-top2 > $work/seeds-top2.log 2>&1;"
      for n in ${TOPN:-4 8}; do
        local opt="xla_gpu_experimental_cost_model_gemm_tiling_options=top=$n,top_from_default=1"
        line+=" $(with_flag "$opt" "timeout -k 20 140 python -m benchmarks.run $seeds --out $work/seeds-top$n" \
          "> $work/seeds-top$n.log 2>&1; timeout -k 20 150 python -m benchmarks.compile_time --out $work/cold-top$n" \
          "--cache-dir $work/cache-top$n -- $sweep > $work/cold-top$n.log 2>&1")"
      done
      echo "$line grep -H -E 'x10:|training would' $work/seeds-*.log $work/cold-*.log" ;;
    tuned)
      local seeds="--suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 --budget-s 110"
      local cases="--suite compare --cases brax-ppo model-free mbmf cd-paper --budget-s 180"
      echo "timeout -k 20 140 python -m benchmarks.run $seeds --out $work/seeds-plain > $work/seeds-plain.log 2>&1;" \
        "CDJAX_COMPILE_MODE=tuned timeout -k 20 140 python -m benchmarks.run $seeds --out $work/seeds-tuned" \
        "> $work/seeds-tuned.log 2>&1;" \
        "$(with_flag xla_gpu_experimental_cost_model_gemm_tiling_options= "timeout -k 20 140 python -m benchmarks.run" \
          "$seeds --out $work/seeds-tilings > $work/seeds-tilings.log 2>&1")" \
        "CDJAX_COMPILE_MODE=tuned timeout -k 20 210 python -m benchmarks.run $cases --out $work/compare-tuned" \
        "> $work/compare-tuned.log 2>&1;" \
        "CDJAX_COMPILE_MODE=tuned timeout -k 20 150 python -m benchmarks.compile_time --out $work/cold-tuned" \
        "--cache-dir $work/cache-tuned -- $sweep > $work/cold-tuned.log 2>&1;" \
        "grep -H -E 'x10:|s/update|training would' $work/seeds-*.log $work/compare-*.log $work/cold-*.log" ;;
    chunks)
      local seeds="--suite seeds --scaling-cases mbmf cd-paper --seed-counts 10 --seed-envs 256 --budget-s 110"
      local cases="--suite compare --cases mbmf cd-paper --budget-s 120" v="benchmarks.variants" line="" x n=0
      for x in plain chunks chunks plain; do
        local run="benchmarks.run"; [ $x = chunks ] && run="$v grad-chunks --"
        line+="timeout -k 20 150 python -m $run $cases --out $work/compare-$x-$((++n)) > $work/compare-$x-$n.log 2>&1; "
      done
      echo "$line timeout -k 20 140 python -m benchmarks.run $seeds --out $work/seeds-plain > $work/seeds-plain.log 2>&1;" \
        "timeout -k 20 140 python -m $v grad-chunks -- $seeds --out $work/seeds-chunks > $work/seeds-chunks.log 2>&1;" \
        "grep -H -E 'x10:|s/update' $work/compare-*.log $work/seeds-*.log" ;;
    kcache)
      local line="" v
      for v in default1 kcache1 kcache2 default2; do
        local env=""; [ "${v:0:6}" = kcache ] && env="XLA_FLAGS=--xla_gpu_kernel_cache_file=$work/$v-kernels.bin"
        line+="$env timeout -k 20 200 python -m benchmarks.compile_time --out $work/$v --cache-dir $work/cache-$v"
        line+=" -- $sweep > $work/$v.log 2>&1; "
      done
      echo "python -m benchmarks.xla_flags --accepts xla_gpu_kernel_cache_file=$work/probe.bin || exit 3; $line" \
        "ls -l $work/*-kernels.bin; grep -H -E 'sweep 1:|compile [0-9.]+ s' $work/*.log" ;;
    timers)
      local vm="TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=gpu_compiler=1,nvptx_compiler=1,compile_module_to_llvm_ir=1"
      echo "$vm timeout -k 20 240 python -m benchmarks.compile_time --out $work/timers --cache-dir $work/cache-timers" \
        "-- $sweep > $work/vlog.txt 2>&1;" \
        "grep -E ' time: |sweep [12]:|compile [0-9.]+ s|ended at' $work/vlog.txt | gzip > $work/timers.log.gz;" \
        "rm -f $work/vlog.txt; python -m benchmarks.xla_timers $work/timers.log.gz --top 16 --json $work/timers.json" \
        "> $work/timers.md; zcat $work/timers.log.gz | grep -E 'sweep 1:|compile [0-9.]+ s'; cat $work/timers.md" ;;
    learn)
      for t in ant halfcheetah reacher; do
        echo "XLA_PYTHON_CLIENT_PREALLOCATE=false timeout -k 20 600 python -m benchmarks.learning --tasks $t" \
          "--frameworks cdjax --variants default --seeds 5 --out $work/learn/$t > $work/learn-$t.log 2>&1 &"
      done
      echo "wait; tail -n 2 $work/learn-*.log" ;;
    *) echo "unknown unit $1: flags, lowered, speed, accept, autotune, levels, tilings, kernels, hlo, parallel, sched, timers, kcache, shares, ab, cublaslt, regions, regions-hlo, chain, chain-e2e, cmdbuf, pdl, concurrent, xla-own, determinism, determinism-cd, outer, chunks, tuned, topn, identity, top1, seeds, hlo-seeds, learn, learn-more, workers, hc-seeds, hc-levels, hc-final, hc-ablate, init, head or head-more" >&2; return 1 ;;
  esac
}

cmd=$(command_of "$unit") || exit 2
mkdir -p "$work" "$out"
. "$(dirname "$0")/../experiments/lease.sh"
ensure_wheels || exit 1
unit_run "$work" "$cmd" "$wait_s" "$t0" "bash benchmarks/compile_units.sh $unit" || exit 0
echo "DONE: unit $unit, exit status $(cat "$work/exit_code"), $(( $(date +%s) - $(cat "$work/started") )) s since it started"
archive=$(cd "$out" && pwd)/$unit.tar.gz
(cd "$work" && find . -name compile_time.json -o -name lowered.json -o -name 'results.*' -o -name 'pixel-*' -o -name '*.log' -o -name '*.log.gz' -o -name 'timers.*' -o -name hlo.tar.gz -o -name rows.jsonl -o -name meta.json \
  | grep -v '/checkpoints/' \
  | tar -czf "$archive" -T -)
cp "$work/unit.log" "$out/$unit.log"
ls -l "$out"
tail -n 30 "$work/unit.log"
