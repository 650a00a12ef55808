/* cochlea all-in-C simulation: sin and cos of one angle at once, inline (sim_sincos).
 *
 * The ideal plants' specialised periods (sim_plant.c) call it where CasADi's code takes the
 * sin and the cos of one joint angle (bench/embedded_bench.py pairs them), and the double
 * build's controller where the scenario allows (simulate.c, SIM_INLINE_TRIG). It is
 * generated_c/cochlea_trig.h's cochlea_sincos, the one the general kernels' ideal plant steps
 * use (source: codegen/cochlea_trig.h; its comment gives the method, its accuracy, at most an
 * ulp from the exact value, and what it needs of the compiler): one header, so that a program
 * compiling generated_c/ kernels and sim_plant.c has one definition. */
#ifndef COCHLEA_SIM_TRIG_H
#define COCHLEA_SIM_TRIG_H

#include "../../generated_c/cochlea_trig.h"

#define sim_sincos cochlea_sincos
#define sim_sin cochlea_sin
#define sim_cos cochlea_cos

#endif
