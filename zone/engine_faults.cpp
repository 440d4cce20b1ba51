// TESTING ONLY: GPU engines that fail mid-run (engine_faults.h).
#include "engine_faults.h"

#include <stdexcept>

namespace zone {

void engine_fault::check(const char* what) {
  if (!fired_ && (!tick || tick() < at_tick)) return;
  fired_ = true;
  if (raise) {
    raise();  // throws (a real device error)
    throw std::logic_error("engine_fault: raise returned without throwing");
  }
  throw std::runtime_error(std::string("CUDA error cudaErrorLaunchFailure (unspecified launch failure) in ") + what +
                           " (injected by --test-fault)");
}

}  // namespace zone
