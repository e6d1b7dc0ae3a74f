package android.app;

import android.content.Context;

public class Instrumentation {
    public Instrumentation() {
        throw new RuntimeException("Stub!");
    }

    public static Application newApplication(Class<?> clazz, Context context)
            throws InstantiationException, IllegalAccessException, ClassNotFoundException {
        throw new RuntimeException("Stub!");
    }
}
