# Imported targets opencv_<module> for the per-module Debian packages (libopencv-<module>-dev), which ship
# headers and libraries but no OpenCVConfig.cmake. Set OpenCV_MIN_MODULES before including.
if(NOT OpenCV_MIN_MODULES)
  set(OpenCV_MIN_MODULES core imgproc imgcodecs)
endif()
find_path(OpenCV_MIN_INCLUDE_DIR opencv2/core.hpp PATH_SUFFIXES opencv4)
if(NOT OpenCV_MIN_INCLUDE_DIR)
  message(FATAL_ERROR "OpenCV headers not found: run deploy/install_deps.sh (needs libopencv-core-dev)")
endif()
foreach(_module IN LISTS OpenCV_MIN_MODULES)
  if(TARGET opencv_${_module})
    continue()
  endif()
  find_library(OpenCV_${_module}_LIBRARY opencv_${_module})
  if(NOT OpenCV_${_module}_LIBRARY)
    message(FATAL_ERROR "libopencv_${_module} not found: run deploy/install_deps.sh (needs libopencv-${_module}-dev)")
  endif()
  add_library(opencv_${_module} SHARED IMPORTED)
  set_target_properties(opencv_${_module} PROPERTIES
    IMPORTED_LOCATION "${OpenCV_${_module}_LIBRARY}"
    INTERFACE_INCLUDE_DIRECTORIES "${OpenCV_MIN_INCLUDE_DIR}")
endforeach()
set(OpenCV_FOUND TRUE)
