# `cmake --build build --target docs`: the API reference, rendered by Doxygen from the `///`
# contracts of the installed headers (docs/embedding.md), into build/docs/html/index.html.
# Not part of the default build; defined only when Doxygen is found (apt-get install doxygen).
find_package(Doxygen QUIET)
if(DOXYGEN_FOUND)
  set(ZONE_DOCS_INPUT
    "${PROJECT_SOURCE_DIR}/docs/embedding.md ${PROJECT_SOURCE_DIR}/interest/interest_space.h ${PROJECT_SOURCE_DIR}/interest/interest.h ${PROJECT_SOURCE_DIR}/interest/interest_tracker.h ${PROJECT_SOURCE_DIR}/interest/host_visibility_engine.h ${PROJECT_SOURCE_DIR}/interest/thread_pool.h ${PROJECT_SOURCE_DIR}/interest/visibility_engine.h ${PROJECT_SOURCE_DIR}/gpu/device.h ${PROJECT_SOURCE_DIR}/gpu/finders.h ${PROJECT_SOURCE_DIR}/gpu/pbig.h ${PROJECT_SOURCE_DIR}/gpu/lbvh.h ${PROJECT_SOURCE_DIR}/gpu/visibility.h")
  set(ZONE_DOCS_OUTPUT ${PROJECT_BINARY_DIR}/docs)
  configure_file(${CMAKE_CURRENT_LIST_DIR}/Doxyfile.in ${PROJECT_BINARY_DIR}/Doxyfile @ONLY)
  add_custom_target(docs
    COMMAND ${CMAKE_COMMAND} -E rm -rf ${ZONE_DOCS_OUTPUT}
    COMMAND ${CMAKE_COMMAND} -E make_directory ${ZONE_DOCS_OUTPUT}
    COMMAND ${DOXYGEN_EXECUTABLE} ${PROJECT_BINARY_DIR}/Doxyfile
    WORKING_DIRECTORY ${PROJECT_SOURCE_DIR}
    COMMENT "Doxygen: the API reference in ${ZONE_DOCS_OUTPUT}/html/index.html"
    VERBATIM)
else()
  message(STATUS "zone: Doxygen not found, no `docs` target (apt-get install doxygen)")
endif()
